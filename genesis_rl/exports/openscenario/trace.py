"""An edge-case record, driven again on lite, as what a scenario file needs: every vehicle's path with time.

A record keeps the scene and the weather of every step, not the vehicles' paths (they follow from the scene,
the seed and the system's controls). :func:`trace_record` replays the record (``replay_record``, so the
trace is checked to be the recorded episode) and reads every vehicle's pose, speed and brake lights at the
start and after every step. At the step the ego comes into contact with a vehicle, that vehicle's pose is
where lite's contact test found it, before lite put both back: the file then meets the ego at the same step.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from genesis_rl.sim.interface import Simulation
from genesis_rl.world.knobs import Weather
from genesis_rl.world.step_record import StepRecord


@dataclass(frozen=True)
class VehicleTrack:
    """One vehicle's start (lite's lane, arc length and next lane, as the scene gave them) and its pose at
    every sample of :attr:`EpisodeTrace.times` (x, y, z of its box centre on the road [m]; yaw
    counter-clockwise from east and pitch nose-up [rad]; speed [m/s]; whether its brake lights were lit, as
    lite lit them from the commanded deceleration: None when unknown)."""

    vehicle_id: int
    role: str
    make: str
    color_name: str
    length: float
    width: float
    height: float
    lane: int
    s: float
    next_lane: int
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    speed: np.ndarray
    braking: np.ndarray | None = None


@dataclass(frozen=True)
class EpisodeTrace:
    """A failing episode as a scenario: vehicles with paths sampled at ``times`` (0 and after every step),
    the knobs of every step (row k is set before step k + 1, at time k dt) and what went wrong."""

    name: str
    map: str
    dt: float
    times: np.ndarray
    vehicles: tuple[VehicleTrack, ...]
    knob_names: tuple[str, ...]
    schedule: np.ndarray
    start_weather: dict[str, float]
    signal_offset: float
    scene_seed: int
    episode_seed: int
    system: dict[str, Any]
    rulebook: Any
    camera: tuple[int, int]
    policy: str
    scene_index: int
    violations: dict[str, float]
    first_collision_step: int | None
    collision_with: int | None
    #: the world the episode ran in (the traffic, the camera's noise, the system's draws); None: the episode seed
    world_seed: int | None = None

    @property
    def duration(self) -> float:
        return float(self.times[-1])


def first_collision(records: list[StepRecord]) -> tuple[int | None, int | None]:
    """(step, other vehicle) of the ego's first collision, or (None, None)."""
    for r in records:
        if r.collision.collided:
            return r.step, r.collision.other_id
    return None, None


#: characters XML 1.0 does not allow (C0 controls but tab, newline and carriage return; surrogates; U+FFFE/FFFF)
_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")


def xml_safe(text: Any) -> str:
    """``text`` with every character XML cannot hold replaced by U+FFFD: a record's strings reach the .xosc, and
    one control character would make the file not well-formed (or stop lxml's writer)."""
    return _NOT_XML.sub("\ufffd", str(text))


def trace_record(rec: dict[str, Any], name: str, weights: str | None = None) -> tuple[EpisodeTrace, dict[str, Any]]:
    """Replay ``rec`` on lite, reading every vehicle's pose at the start and after every step; returns the
    trace and the replay's result (``reproduced`` says whether the replay is the recorded episode)."""
    from genesis_rl.campaigns.records import recorded_world_seed, replay_record  # local: torch, the renderer
    from genesis_rl.sim.lite.backend import LiteSimulation

    samples: list[np.ndarray] = []
    lights: list[np.ndarray] = []
    dt_box: list[float] = []

    def observe(sim: Simulation) -> None:
        assert isinstance(sim, LiteSimulation)  # replay_record drives lite only
        dt_box[:] = [sim.dt]
        rows = np.array([[a.x, a.y, a.z, a.yaw, a.pitch, a.speed] for a in sim.actors()])
        for j, (x, y, yaw) in sim.traffic.ego_contact_poses.items():
            rows[j, [0, 1, 3]] = x, y, yaw  # where the ego hit it, not where lite put it back after the contact
        samples.append(rows)
        lights.append(np.array(sim.traffic.braking, dtype=bool))  # what the renderer drew: the detector saw it

    result = replay_record(rec, weights=weights, keep_frames=False, observer=observe)
    poses = np.stack(samples)  # (steps + 1, vehicles, 6)
    lit = np.stack(lights)  # (steps + 1, vehicles)
    scene = rec["scene"]
    from genesis_rl.world.scenes.vehicles import MAKES

    tracks = []
    for i, v in enumerate(scene["vehicles"]):
        m = MAKES[v["make"]]
        tracks.append(VehicleTrack(
            vehicle_id=i, role=xml_safe(v["role"]), make=v["make"], color_name=xml_safe(v["color_name"]),
            length=m.length,
            width=m.width, height=m.height, lane=int(v["lane"]), s=float(v["s"]), next_lane=int(v["next_lane"]),
            x=poses[:, i, 0], y=poses[:, i, 1], z=poses[:, i, 2], yaw=np.unwrap(poses[:, i, 3]),
            pitch=poses[:, i, 4], speed=poses[:, i, 5], braking=lit[:, i]))
    dt = dt_box[0]
    step, other = first_collision(result["records"])
    trace = EpisodeTrace(
        name=xml_safe(name), map=xml_safe(scene["map"]), dt=dt, times=np.round(np.arange(len(poses)) * dt, 9),
        vehicles=tuple(tracks),
        knob_names=tuple(rec["knobs"]), schedule=np.asarray(rec["schedule"], dtype=np.float64),
        start_weather=Weather.from_recorded(rec["start_weather"]).as_dict(),
        signal_offset=float(scene["signal_offset"]), scene_seed=int(scene["seed"]),
        episode_seed=int(rec["episode_seed"]), rulebook=rec["rulebook"],
        system={"spec": xml_safe(rec["system"]["spec"]), "kwargs": dict(rec["system"].get("kwargs") or {}),
                "identity": dict(rec["system"].get("identity") or {})},
        camera=(int(rec["camera"]["width"]), int(rec["camera"]["height"])), policy=xml_safe(rec.get("policy", "")),
        scene_index=int(scene["index"]), violations=dict(result["violations"]),
        first_collision_step=step, collision_with=other, world_seed=recorded_world_seed(rec))
    return trace, result
