"""Oriented-box collision tests (separating axis theorem), with a cheap bounding-circle broad phase."""

from __future__ import annotations

import numpy as np


def box_corners(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = length / 2, width / 2
    local = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    return local @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two convex quads (4x2 corners) overlap (touching counts as no overlap)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        axes = np.column_stack([-edges[:, 1], edges[:, 0]])
        pa, pb = a @ axes.T, b @ axes.T
        if np.any((pa.max(0) <= pb.min(0)) | (pb.max(0) <= pa.min(0))):
            return False
    return True


def colliding_pairs(
    x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray
) -> list[tuple[int, int]]:
    """All pairs (i < j) whose oriented boxes overlap."""
    r = 0.5 * np.hypot(length, width)
    dx = x[:, None] - x[None, :]
    dy = y[:, None] - y[None, :]
    near = dx * dx + dy * dy < (r[:, None] + r[None, :]) ** 2
    ii, jj = np.nonzero(np.triu(near, 1))
    out = []
    for i, j in zip(ii.tolist(), jj.tolist(), strict=True):
        if boxes_overlap(
            box_corners(x[i], y[i], yaw[i], length[i], width[i]), box_corners(x[j], y[j], yaw[j], length[j], width[j])
        ):
            out.append((i, j))
    return out
