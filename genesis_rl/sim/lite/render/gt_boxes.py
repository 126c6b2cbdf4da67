"""Ground-truth boxes of the vehicles in a rendered frame, from their label pixels (occlusion-aware).

Each vehicle's 3D box is projected to find the window in which its label pixels are searched; the box is the
extent of those pixels, its distance the nearest depth among them, and its visible fraction their count
against the projected box. Plain numpy and OpenCV: works on any labels and depth images, GL or not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from genesis_rl.sim.interface import CameraConfig, GroundTruthBox
from genesis_rl.sim.lite.render.view import camera_axes

#: vehicles farther than this from the camera (metres, on the ground plane) get no box
MAX_BOX_RANGE = 150.0
#: fewer visible pixels than this: not a box
MIN_BOX_PIXELS = 12
#: share of a vehicle's projected 3D-box rectangle that its silhouette covers (for visible_fraction)
SILHOUETTE_FILL = 0.72

_CORNER_A = np.array([-1, -1, -1, -1, 1, 1, 1, 1], np.float64)[:, None]  # along the vehicle's length
_CORNER_B = np.array([-1, -1, 1, 1, -1, -1, 1, 1], np.float64)[:, None]  # along its width


def ground_truth_boxes(
    camera: CameraConfig,
    near: float,
    poses: np.ndarray,
    dims: np.ndarray,
    ids: Sequence[int],
    vehicle_labels: Sequence[int],
    cpos: np.ndarray,
    cyaw: float,
    cpitch: float,
    labels: np.ndarray,
    depth: np.ndarray,
) -> list[GroundTruthBox]:
    """Boxes of vehicles ``ids`` (rows of ``poses`` (x, y, z, yaw, ...) and ``dims`` (length, width, height)),
    drawn with label ``vehicle_labels[k]`` into ``labels``, seen by a camera at ``cpos`` with yaw ``cyaw`` and
    pitch ``cpitch`` whose near plane is ``near`` metres away; ``depth`` is metric, along the optical axis.

    The projection is done for all vehicles at once (one numpy expression instead of some forty small ones
    per vehicle: 80 us per vehicle before, 25 now)."""
    if not ids:
        return []
    h, w = labels.shape[:2]
    f = camera.focal_px
    fwd, right, up = camera_axes(cyaw, cpitch)
    sel = np.asarray(ids)
    x, y, z = poses[sel, 0], poses[sel, 1], poses[sel, 2]
    ln, wd, ht = (dims[sel, k][:, None, None] for k in range(3))
    yaw = poses[sel, 3]
    c = np.array([math.cos(float(a)) for a in yaw])
    s = np.array([math.sin(float(a)) for a in yaw])
    zero = np.zeros(len(ids))
    ex = np.stack([c, s, zero], axis=1)[:, None, :]  # (N, 1, 3)
    ey = np.stack([-s, c, zero], axis=1)[:, None, :]
    zz = np.zeros((len(ids), 8, 3))
    zz[:, 1::2, 2] = ht[:, :, 0]
    base = np.stack([x, y, z], axis=1)[:, None, :]
    # the 8 corners, ordered a, b, z as (-1|1) x (-1|1) x (0|ht), relative to the camera
    corners = (base + ex * _CORNER_A * ln / 2 + ey * _CORNER_B * wd / 2 + zz) - cpos
    zc = corners @ fwd  # (N, 8)
    front = zc > near
    with np.errstate(divide="ignore", invalid="ignore"):
        u_all = w / 2 + f * (corners @ right) / zc
        v_all = h / 2 - f * (corners @ up) / zc
    u_min = np.where(front, u_all, np.inf).min(axis=1)
    u_max = np.where(front, u_all, -np.inf).max(axis=1)
    v_min = np.where(front, v_all, np.inf).min(axis=1)
    v_max = np.where(front, v_all, -np.inf).max(axis=1)
    all_front = front.all(axis=1)
    seen = (np.hypot(x - cpos[0], y - cpos[1]) <= MAX_BOX_RANGE) & front.any(axis=1)
    out: list[GroundTruthBox] = []
    for k in np.flatnonzero(seen).tolist():
        u0, u1, v0, v1 = float(u_min[k]), float(u_max[k]), float(v_min[k]), float(v_max[k])
        if not all_front[k]:  # partly behind the camera: the box reaches the border it crosses
            u0 = 0.0 if u0 <= w / 2 else u0
            u1 = float(w) if u1 >= w / 2 else u1
            v0, v1 = max(0.0, v0), min(float(h), v1)
        truncated = bool(u0 < 0 or v0 < 0 or u1 > w or v1 > h or not all_front[k])
        ix0, iy0 = max(0, math.floor(u0) - 1), max(0, math.floor(v0) - 1)
        ix1, iy1 = min(w, math.ceil(u1) + 1), min(h, math.ceil(v1) + 1)
        if ix1 <= ix0 or iy1 <= iy0:
            continue
        # its label's pixels in the window (OpenCV: four calls instead of eight numpy ones)
        # (OpenCV takes the label as a scalar; its stubs know only arrays)
        mask = cv2.compare(labels[iy0:iy1, ix0:ix1], vehicle_labels[k], cv2.CMP_EQ)  # type: ignore[call-overload]
        count = cv2.countNonZero(mask)
        if count < MIN_BOX_PIXELS:
            continue
        bx, by, bw, bh = cv2.boundingRect(mask)
        dist = float(cv2.minMaxLoc(depth[iy0:iy1, ix0:ix1], mask)[0])
        area = max(1.0, (min(u1, w) - max(u0, 0)) * (min(v1, h) - max(v0, 0)))
        frac = float(min(1.0, count / (SILHOUETTE_FILL * area)))
        out.append(
            GroundTruthBox(
                vehicle_id=int(ids[k]),
                x0=int(ix0 + bx),
                y0=int(iy0 + by),
                x1=int(ix0 + bx + bw),
                y1=int(iy0 + by + bh),
                distance=dist,
                visible_fraction=frac,
                truncated=truncated,
            )
        )
    return out
