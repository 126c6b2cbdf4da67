"""CARLA's frame <-> ours. CARLA (Unreal) is left-handed: x forward/east, y right/south, z up, yaw in degrees
clockwise seen from above. GENESIS-RL (catalog, ActorState) is right-handed: x east, y north, z up, yaw in
radians counter-clockwise. So y and yaw change sign; pitch (nose up positive) is the same in both."""

from __future__ import annotations

import math
from typing import Any

from genesis_rl.sim.carla._carla import require_carla


def wrap_pi(angle: float) -> float:
    """Angle in (-pi, pi]."""
    a = math.fmod(angle + math.pi, 2.0 * math.pi)
    return (a + 2.0 * math.pi if a <= 0.0 else a) - math.pi


def pose_from_carla(transform: Any) -> tuple[float, float, float, float, float]:
    """(x, y, z, yaw [rad, CCW], pitch [rad]) in our frame from a ``carla.Transform``."""
    loc, rot = transform.location, transform.rotation
    return (float(loc.x), -float(loc.y), float(loc.z), wrap_pi(-math.radians(rot.yaw)), math.radians(rot.pitch))


def transform_to_carla(x: float, y: float, z: float, yaw: float, pitch: float = 0.0) -> Any:
    """A ``carla.Transform`` from a pose in our frame (yaw, pitch in radians)."""
    carla = require_carla()
    return carla.Transform(carla.Location(x=float(x), y=-float(y), z=float(z)),
                           carla.Rotation(pitch=math.degrees(pitch), yaw=-math.degrees(yaw), roll=0.0))


def camera_mount(mount_x: float, mount_y: float, mount_z: float, pitch_deg: float) -> Any:
    """The camera's transform relative to the ego (our mount: x forward, y left; CARLA's: y right)."""
    carla = require_carla()
    return carla.Transform(carla.Location(x=float(mount_x), y=-float(mount_y), z=float(mount_z)),
                           carla.Rotation(pitch=float(pitch_deg)))
