"""Oriented-box collision tests (separating axis theorem), with a cheap bounding-circle broad phase."""

from __future__ import annotations

import numpy as np

from genesis_rl.world.scenes.placement import box_corners, boxes_overlap

__all__ = ["all_corners", "box_corners", "boxes_overlap", "colliding_pairs"]


def all_corners(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(n, 4, 2) corners of n oriented boxes, in the order of :func:`box_corners`."""
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    lx = np.array([0.5, 0.5, -0.5, -0.5]) * length[:, None]
    ly = np.array([0.5, -0.5, -0.5, 0.5]) * width[:, None]
    return np.stack([x[:, None] + lx * c - ly * s, y[:, None] + lx * s + ly * c], axis=-1)


def colliding_pairs(
    x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray
) -> list[tuple[int, int]]:
    """All pairs (i < j) whose oriented boxes overlap: bounding circles first, then SAT on the
    candidates, vectorised over pairs."""
    r = 0.5 * np.hypot(length, width)
    dx = x[:, None] - x[None, :]
    dy = y[:, None] - y[None, :]
    near = dx * dx + dy * dy < (r[:, None] + r[None, :]) ** 2
    ii, jj = np.nonzero(np.triu(near, 1))
    if len(ii) == 0:
        return []
    corners = all_corners(x, y, yaw, length, width)
    a, b = corners[ii], corners[jj]  # (p, 4, 2)
    # candidate axes: the edge normals of both boxes (two per box suffice for rectangles)
    axes = np.concatenate([a[:, 1:3] - a[:, 0:2], b[:, 1:3] - b[:, 0:2]], axis=1)  # (p, 4, 2)
    axes = np.stack([-axes[..., 1], axes[..., 0]], axis=-1)
    pa = np.einsum("pkd,pad->pka", a, axes)  # (p, corners, axes)
    pb = np.einsum("pkd,pad->pka", b, axes)
    separated = (pa.max(1) <= pb.min(1)) | (pb.max(1) <= pa.min(1))
    hit = ~separated.any(axis=1)
    return [(int(i), int(j)) for i, j in zip(ii[hit], jj[hit], strict=True)]
