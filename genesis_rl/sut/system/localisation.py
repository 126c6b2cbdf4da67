"""Depth localisation: a detection's box + the depth image + the camera intrinsics -> a 3D point.

The paper reads the depth at the box centre. A single pixel is fragile (the centre of a car seen through
its windows, or a gap between box and body, reads the background), so we take a low quantile of the
depth in a central window of the box: robust to background pixels (they are farther) and to noise.
"""

from __future__ import annotations

import math

import numpy as np

from genesis_rl.sim.interface import CameraConfig

#: central window of the box used for depth: fractions of its width and height
WINDOW_X = (0.3, 0.7)
WINDOW_Y = (0.35, 0.8)
DEPTH_QUANTILE = 0.3


def box_depth(depth: np.ndarray, box: tuple[float, float, float, float], max_range: float = 200.0) -> float:
    """Robust depth [m] along the optical axis inside ``box`` (x0, y0, x1, y1 in pixels); inf if none."""
    h, w = depth.shape
    x0, y0, x1, y1 = box
    bw, bh = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
    # plain-Python clipping (np.clip on scalars cost more than the quantile); same integers
    u0 = min(max(math.floor(x0 + WINDOW_X[0] * bw), 0), w - 1)
    u1 = min(max(math.ceil(x0 + WINDOW_X[1] * bw), u0 + 1), w)
    v0 = min(max(math.floor(y0 + WINDOW_Y[0] * bh), 0), h - 1)
    v1 = min(max(math.ceil(y0 + WINDOW_Y[1] * bh), v0 + 1), h)
    patch = depth[v0:v1, u0:u1]
    patch = patch[np.isfinite(patch) & (patch > 0.0) & (patch < max_range)]
    if patch.size == 0:
        return float("inf")
    return float(np.quantile(patch, DEPTH_QUANTILE))


Box = tuple[float, float, float, float]


def localise(box: Box, depth_m: float, camera: CameraConfig) -> tuple[float, float, float]:
    """Back-project the box centre at ``depth_m`` into the ego frame (x forward, y left, z up), with the
    camera's mount offsets; camera pitch is taken into account."""
    f = camera.focal_px
    u = 0.5 * (box[0] + box[2])
    v = 0.5 * (box[1] + box[3])
    # camera frame: forward = depth, left = -(u - cx) * depth / f, up = -(v - cy) * depth / f
    fwd = depth_m
    left = -(u - camera.width / 2.0) * depth_m / f
    up = -(v - camera.height / 2.0) * depth_m / f
    p = np.radians(camera.pitch_deg)
    x = fwd * np.cos(p) - up * np.sin(p)
    z = fwd * np.sin(p) + up * np.cos(p)
    return (float(x + camera.mount_x), float(left + camera.mount_y), float(z + camera.mount_z))
