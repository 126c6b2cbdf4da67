"""Where the ego's camera is and what it can see: its pose from the ego's, its axes, and a frustum test.

Plain numpy, shared by the GL shell (which hides vehicles out of view before drawing) and the ground-truth
boxes (which project vehicles with the same axes).
"""

from __future__ import annotations

import math

import numpy as np

from genesis_rl.sim.interface import CameraConfig


def camera_axes(cyaw: float, cpitch: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The camera's forward, right and up unit vectors in the world (yaw CCW from +x, pitch up)."""
    cy_, sy_ = math.cos(cyaw), math.sin(cyaw)
    cp, sp = math.cos(cpitch), math.sin(cpitch)
    fwd = np.array([cp * cy_, cp * sy_, sp])
    right = np.array([sy_, -cy_, 0.0])
    up = np.array([-sp * cy_, -sp * sy_, cp])
    return fwd, right, up


def camera_pose(pose: np.ndarray, camera: CameraConfig) -> tuple[np.ndarray, float, float]:
    """The camera's world position, yaw and pitch (radians) on an ego at ``pose`` (x, y, z, yaw, pitch)."""
    x, y, z, yaw, pitch = (float(v) for v in pose[:5])
    cy_, sy_ = math.cos(yaw), math.sin(yaw)
    cp = math.cos(pitch)
    f0, f1, f2 = cp * cy_, cp * sy_, math.sin(pitch)  # forward
    l0, l1, l2 = -sy_, cy_, 0.0  # left
    b0, b1, b2 = -l0, -l1, -l2
    # up = forward x (-left), as np.cross computes it, pointing up
    u0, u1, u2 = f1 * b2 - f2 * b1, f2 * b0 - f0 * b2, f0 * b1 - f1 * b0
    if u2 < 0:
        u0, u1, u2 = -u0, -u1, -u2
    mx, my, mz = camera.mount_x, camera.mount_y, camera.mount_z
    pos = np.array(
        [x + f0 * mx + l0 * my + u0 * mz, y + f1 * mx + l1 * my + u1 * mz, z + f2 * mx + l2 * my + u2 * mz]
    )
    return pos, yaw, pitch + math.radians(camera.pitch_deg)


def outside_view(
    poses: np.ndarray,
    dims: np.ndarray,
    fov_deg: float,
    cpos: np.ndarray,
    cyaw: float,
    cpitch: float,
    shadow_len: float,
) -> np.ndarray:
    """Which vehicles lie wholly behind the camera or beyond the side planes of its frustum: a sphere around
    each (its shadow, ``shadow_len`` metres long, included) against the camera's near and two side planes."""
    fwd, right, _ = camera_axes(cyaw, cpitch)
    centre = poses[:, :3] + np.column_stack([np.zeros((len(poses), 2)), dims[:, 2] / 2])
    rel = centre - cpos[None, :]
    radius = 0.5 * np.sqrt((dims[:, :3] ** 2).sum(axis=1)) + shadow_len + 1.0
    half = math.radians(fov_deg) / 2.0
    sh, ch = math.sin(half), math.cos(half)
    out = np.zeros(len(poses), bool)
    for normal in (fwd, fwd * sh + right * ch, fwd * sh - right * ch):  # inward normals of the planes
        out |= rel @ normal < -radius
    return out
