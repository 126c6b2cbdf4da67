"""Ground-truth 2D boxes: a vehicle's 3D bounding box through the camera, kept to its unoccluded pixels.

CARLA gives each actor an oriented ``BoundingBox`` (centre and rotation relative to the actor, half extents).
We express it in the camera's optical frame with ``carla.Transform`` matrices, project its corners (clipped at
the near plane, so a box partly behind the camera still gets the right border), and then cast one ray per
pixel of that rectangle through the box (slab test). The depth camera measures depth along the optical axis,
and our rays have unit z, so a ray's parameter *is* depth: a pixel whose ray enters the box but whose depth
is nearer than the entry point (minus a tolerance) is hidden by something else; one that lands between entry
and exit belongs to the vehicle. The box is the tight rectangle of those pixels, as the lite renderer does
with its label image.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from genesis_rl.sim.carla._carla import require_carla
from genesis_rl.sim.interface import GroundTruthBox

#: Unreal camera axes (x forward, y right, z up) -> optical axes (x right, y down, z forward)
UE_TO_OPTICAL = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
NEAR = 0.3  # [m] near plane
DEPTH_TOL = 0.3  # [m] mesh parts poking out of the bounding box (mirrors) and depth quantisation
MIN_BOX_PIXELS = 12  # fewer visible pixels than this: not a box (as the lite renderer)

_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


@dataclass(frozen=True)
class CameraBox:
    """An oriented box in the optical frame: centre, axes (columns: the box's x, y, z) and half extents."""

    center: np.ndarray
    axes: np.ndarray
    extent: np.ndarray

    def vertices(self) -> np.ndarray:
        """The 8 corners, shape (8, 3)."""
        return self.center + (_SIGNS * self.extent) @ self.axes.T


def _matrix(transform: Any) -> np.ndarray:
    return np.asarray(transform.get_matrix(), dtype=np.float64)


def world_to_optical(points: np.ndarray, camera_transform: Any) -> np.ndarray:
    """World points (N, 3) in CARLA's frame -> the camera's optical frame (x right, y down, z forward)."""
    inv = np.asarray(camera_transform.get_inverse_matrix(), dtype=np.float64)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    local = p @ inv[:3, :3].T + inv[:3, 3]
    return local @ UE_TO_OPTICAL.T


def box_in_camera(bbox: Any, actor_transform: Any, camera_transform: Any) -> CameraBox:
    """An actor's ``carla.BoundingBox`` (relative to the actor) in the optical frame of ``camera_transform``."""
    carla = require_carla()
    box_local = carla.Transform(bbox.location, bbox.rotation)
    inv = np.asarray(camera_transform.get_inverse_matrix(), dtype=np.float64)
    m = inv @ _matrix(actor_transform) @ _matrix(box_local)
    axes = UE_TO_OPTICAL @ m[:3, :3]
    center = UE_TO_OPTICAL @ m[:3, 3]
    extent = np.array([bbox.extent.x, bbox.extent.y, bbox.extent.z], dtype=np.float64)
    return CameraBox(center, axes, extent)


def project_box(box: CameraBox, k: np.ndarray, width: int, height: int,
                near: float = NEAR) -> tuple[float, float, float, float, bool] | None:
    """The box's image rectangle (u0, v0, u1, v1) in pixels, clipped to the image, and whether it was
    truncated (by the border or the near plane); None when nothing of it is in view."""
    v = box.vertices()
    front = v[:, 2] > near
    if not front.any():
        return None
    pts = [v[front]]
    i_idx, j_idx = np.nonzero(front[:, None] & ~front[None, :])
    if len(i_idx):  # the clipped box's new corners lie on segments between a front and a back corner
        a, b = v[i_idx], v[j_idx]
        t = (near - a[:, 2]) / (b[:, 2] - a[:, 2])
        pts.append(a + t[:, None] * (b - a))
    p = np.concatenate(pts) @ np.asarray(k, dtype=np.float64).T
    u, w = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    u0, u1, v0, v1 = float(u.min()), float(u.max()), float(w.min()), float(w.max())
    truncated = bool(not front.all() or u0 < 0 or v0 < 0 or u1 > width or v1 > height)
    u0, u1 = max(u0, 0.0), min(u1, float(width))
    v0, v1 = max(v0, 0.0), min(v1, float(height))
    if u1 <= u0 or v1 <= v0:
        return None
    return u0, v0, u1, v1, truncated


def ray_box_depths(box: CameraBox, k: np.ndarray, x0: int, y0: int, x1: int,
                   y1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the pixel centres of rows y0..y1-1 and columns x0..x1-1: depth where the ray enters and leaves
    the box, and whether it hits it at all (arrays of shape (y1 - y0, x1 - x0))."""
    kinv = np.linalg.inv(np.asarray(k, dtype=np.float64))
    uu, vv = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
    dirs = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ kinv.T  # z component stays 1: t is depth
    d = dirs @ box.axes  # ray directions in the box frame
    o = -box.center @ box.axes  # camera centre in the box frame
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-box.extent - o) / d
        t2 = (box.extent - o) / d
    parallel = np.abs(d) < 1e-12
    inside = np.abs(o) <= box.extent
    lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    t_in, t_out = lo.max(axis=-1), hi.min(axis=-1)
    hit = (t_out >= t_in) & (t_out > NEAR)
    return np.maximum(t_in, NEAR), t_out, hit


def ground_truth_box(vehicle_id: int, box: CameraBox, k: np.ndarray, depth: np.ndarray, *, near: float = NEAR,
                     tol: float = DEPTH_TOL, min_pixels: int = MIN_BOX_PIXELS) -> GroundTruthBox | None:
    """The visible part of ``box`` in a depth image (H, W) in metres, or None when (almost) all hidden."""
    height, width = depth.shape
    proj = project_box(box, k, width, height, near)
    if proj is None:
        return None
    u0, v0, u1, v1, truncated = proj
    ix0, iy0 = max(0, math.floor(u0)), max(0, math.floor(v0))
    ix1, iy1 = min(width, math.ceil(u1)), min(height, math.ceil(v1))
    t_in, t_out, hit = ray_box_depths(box, k, ix0, iy0, ix1, iy1)
    patch = np.asarray(depth[iy0:iy1, ix0:ix1], dtype=np.float64)
    hidden = hit & (patch < t_in - tol)
    own = hit & ~hidden & (patch <= t_out + tol)
    count = int(own.sum())
    if count < min_pixels:
        return None
    rows = np.flatnonzero(own.any(axis=1))
    cols = np.flatnonzero(own.any(axis=0))
    return GroundTruthBox(
        vehicle_id=int(vehicle_id),
        x0=int(ix0 + cols[0]),
        y0=int(iy0 + rows[0]),
        x1=int(ix0 + cols[-1] + 1),
        y1=int(iy0 + rows[-1] + 1),
        distance=float(patch[own].min()),
        visible_fraction=float(1.0 - hidden.sum() / max(1, int(hit.sum()))),
        truncated=truncated,
    )


def ground_truth_boxes(vehicles: Iterable[tuple[int, Any, Any]], camera_transform: Any, k: np.ndarray,
                       depth: np.ndarray, max_range: float = 200.0) -> list[GroundTruthBox]:
    """Boxes of the visible vehicles among ``(vehicle_id, bounding_box, actor_transform)`` (leave out the
    camera's own vehicle: the camera sits inside its box)."""
    out = []
    for vid, bbox, tf in vehicles:
        box = box_in_camera(bbox, tf, camera_transform)
        if box.center[2] < -max(box.extent) or float(np.linalg.norm(box.center)) > max_range:
            continue
        gt = ground_truth_box(vid, box, k, depth)
        if gt is not None:
            out.append(gt)
    return sorted(out, key=lambda b: b.vehicle_id)
