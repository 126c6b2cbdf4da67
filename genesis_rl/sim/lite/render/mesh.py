"""Indexed triangle meshes as plain numpy arrays: what the static-scene builder makes and the GL shell uploads.

Every vertex carries a position, a unit normal and an RGBA colour whose alpha is the surface's label (see
``labels.py``). Nothing here touches Panda3D, so the scene can be built and checked without a GL context.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike


class Mesh:
    """Accumulates indexed triangles (numpy chunks) with per-vertex colour; alpha = label."""

    def __init__(self) -> None:
        self.pos: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.col: list[np.ndarray] = []
        self.idx: list[np.ndarray] = []
        self.n = 0

    def add(self, pos: ArrayLike, nrm: ArrayLike, col: ArrayLike, idx: ArrayLike, label: int) -> None:
        pos = np.asarray(pos, np.float32).reshape(-1, 3)
        k = len(pos)
        nrm = np.broadcast_to(np.asarray(nrm, np.float32), (k, 3))
        rgb = np.broadcast_to(np.asarray(col, np.float64), (k, 3))
        c = np.empty((k, 4), np.uint8)
        c[:, :3] = np.clip(np.rint(rgb * 255.0), 0, 255)
        c[:, 3] = label
        self.pos.append(pos)
        self.nrm.append(np.array(nrm))
        self.col.append(c)
        self.idx.append(np.asarray(idx, np.int64).reshape(-1) + self.n)
        self.n += k

    def quad(self, a: ArrayLike, b: ArrayLike, c: ArrayLike, d: ArrayLike, col: ArrayLike, label: int) -> None:
        """Two triangles a-b-c, a-c-d, with the flat normal of a-b-c (counter-clockwise seen from outside)."""
        p = np.array([a, b, c, d], np.float64)
        nrm = np.cross(p[1] - p[0], p[2] - p[0])
        nrm /= max(1e-9, float(np.linalg.norm(nrm)))
        self.add(p, nrm, col, np.array([0, 1, 2, 0, 2, 3]), label)

    def strip(self, left: np.ndarray, right: np.ndarray, col: ArrayLike, label: int) -> None:
        """Quads between two (N, 3) polylines, facing up (left is to the left of the direction of travel)."""
        n = len(left)
        if n < 2:
            return
        pos = np.concatenate([right, left])
        i = np.arange(n - 1)
        tri = np.stack([i, i + 1, n + i + 1, i, n + i + 1, n + i], axis=1)
        self.add(pos, (0.0, 0.0, 1.0), col, tri, label)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pos (n, 3) float32, nrm (n, 3) float32, col (n, 4) uint8, triangles (m, 3) int64), all chunks."""
        if not self.n:
            return (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros((0, 4), np.uint8),
                    np.zeros((0, 3), np.int64))
        pos, nrm, col = np.concatenate(self.pos), np.concatenate(self.nrm), np.concatenate(self.col)
        return pos, nrm, col, np.concatenate(self.idx).reshape(-1, 3)

    @property
    def triangle_count(self) -> int:
        return sum(len(i) for i in self.idx) // 3

    def tiles(self, size: float) -> dict[tuple[int, int], Mesh]:
        """Split into square ground tiles of ``size`` metres by triangle centroid, so that the renderer can
        cull what the camera does not see (one flattened mesh for a whole map made llvmpipe transform
        every tree on the map each frame). Triangle order within a tile is kept."""
        if not self.n:
            return {}
        pos, nrm, col, tri = self.arrays()
        key = np.floor(pos[tri].mean(axis=1)[:, :2] / size).astype(np.int64)
        out: dict[tuple[int, int], Mesh] = {}
        for kx, ky in np.unique(key, axis=0):
            t = tri[(key[:, 0] == kx) & (key[:, 1] == ky)]
            used, local = np.unique(t.ravel(), return_inverse=True)
            m = Mesh()
            m.pos, m.nrm, m.col = [pos[used]], [nrm[used]], [col[used]]
            m.idx = [local.astype(np.int64)]
            m.n = len(used)
            out[(int(kx), int(ky))] = m
        return out


def box(
    m: Mesh,
    cx: float,
    cy: float,
    z0: float,
    yaw: float,
    w: float,
    d: float,
    h: float,
    col: ArrayLike,
    label: int,
    top: bool = True,
) -> None:
    """Box with footprint w (along yaw) x d, from z0 to z0 + h."""
    c, s = math.cos(yaw), math.sin(yaw)
    ax = np.array([c, s, 0.0]) * w / 2
    ay = np.array([-s, c, 0.0]) * d / 2
    base = np.array([cx, cy, z0])
    up = np.array([0.0, 0.0, h])
    corners = [base + ax + ay, base - ax + ay, base - ax - ay, base + ax - ay]  # counter-clockwise
    rgb = np.asarray(col, np.float64)
    for k in range(4):
        p, q = corners[k], corners[(k + 1) % 4]
        shade = 0.85 + 0.15 * ((k % 2) == 0)
        m.quad(q, p, p + up, q + up, rgb * shade, label)
    if top:
        a, b, c_, d_ = (cr + up for cr in corners)
        m.quad(a, b, c_, d_, rgb * 0.95, label)
