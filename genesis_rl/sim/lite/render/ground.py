"""The terrain under the roads: a height-field grid, and a coarser twin of it for far-away blocks.

The grid's cells are some 8-13 m; seen from 200 m and more they are a few pixels, and on the highway map
its ~10k triangles in view were the largest part of the far scenery llvmpipe had to set up each frame.
Far blocks therefore draw every ``step``-th grid line only, on the very same vertices (heights, normals and
colours), so that where a coarse block meets a full-detail tile the two surfaces share their corners and
part by no more than the terrain's curvature over one coarse cell (under 6 cm on the highway map's hills).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from genesis_rl.sim.lite.maps.lane_graph import RoadMap

#: every how many grid lines the far blocks keep
FAR_GROUND_STEP = 2


@dataclass(frozen=True)
class GroundGrid:
    """Vertices of the terrain grid, row-major ((ny, nx) rows of x, y, z; unit normals; RGB in 0..1)."""

    pos: np.ndarray
    nrm: np.ndarray
    col: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.pos.shape[0], self.pos.shape[1]


def ground_grid(rm: RoadMap, rng: np.random.Generator, depth_below_road: float) -> GroundGrid:
    """The map's terrain, ``depth_below_road`` metres under the road surface, with a seeded colour mottle."""
    xmin, ymin, xmax, ymax = rm.bounds
    cell = max(8.0, max(xmax - xmin, ymax - ymin) / 110.0)
    nx = int(math.ceil((xmax - xmin) / cell)) + 1
    ny = int(math.ceil((ymax - ymin) / cell)) + 1
    gx, gy = np.meshgrid(np.linspace(xmin, xmax, nx), np.linspace(ymin, ymax, ny))
    gz = np.asarray(rm.elevation(gx.ravel(), gy.ravel()), np.float64) * np.ones(gx.size)
    gz = gz - depth_below_road
    zz = gz.reshape(ny, nx)
    dzdy, dzdx = np.gradient(zz, (ymax - ymin) / (ny - 1), (xmax - xmin) / (nx - 1))
    nrm = np.stack([-dzdx.ravel(), -dzdy.ravel(), np.ones(gx.size)], axis=1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    gcol = np.asarray(rm.ground_color) * (0.92 + 0.16 * rng.random((gx.size, 1)))
    pos = np.column_stack([gx.ravel(), gy.ravel(), gz])
    return GroundGrid(pos.reshape(ny, nx, 3), nrm.reshape(ny, nx, 3), gcol.reshape(ny, nx, 3))


def cell_triangles(nx: int, ny: int) -> np.ndarray:
    """Two counter-clockwise triangles per cell of an (ny, nx) vertex grid, cell by cell, row-major."""
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    return np.stack([a, a + 1, a + nx + 1, a, a + nx + 1, a + nx], axis=1).reshape(-1, 3)


def _lines(n: int, step: int) -> np.ndarray:
    return np.unique(np.r_[np.arange(0, n, step), n - 1])


def coarse_blocks(
    grid: GroundGrid, step: int, block_m: float
) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per square block of ``block_m`` metres: (pos, nrm, col, triangles) of the coarse grid over it.

    The full-detail grid goes to blocks triangle by triangle, by centroid (as ``Mesh.tiles`` in mesh.py cuts it); a
    coarse cell goes to every block that one of its full-detail triangles went to, so that a coarse block
    covers all the ground that its full-detail self covered and no sky shows through at a seam (a coarse
    cell shared by two coarse blocks is drawn twice, identically: the depth test keeps the first).
    """
    ny, nx = grid.shape
    rows, cols = _lines(ny, step), _lines(nx, step)
    # block of each full-detail triangle, from its float32 centroid exactly as Mesh.tiles computes it
    pos32 = grid.pos.reshape(-1, 3).astype(np.float32)
    fine = cell_triangles(nx, ny)
    key = np.floor(pos32[fine].mean(axis=1)[:, :2] / block_m).astype(np.int64)
    # the coarse cell each full-detail triangle lies in (two triangles per cell, row-major)
    j, i = np.divmod(np.repeat(np.arange((ny - 1) * (nx - 1)), 2), nx - 1)
    cj = np.searchsorted(rows, j, side="right") - 1
    ci = np.searchsorted(cols, i, side="right") - 1
    coarse_cell = cj * (len(cols) - 1) + ci
    pairs = np.unique(np.column_stack([key, coarse_cell]), axis=0)

    sub = (rows[:, None] * nx + cols[None, :]).ravel()
    c_pos = grid.pos.reshape(-1, 3)[sub]
    c_nrm = grid.nrm.reshape(-1, 3)[sub]
    c_col = grid.col.reshape(-1, 3)[sub]
    c_tri = cell_triangles(len(cols), len(rows)).reshape(-1, 2, 3)
    out: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    for bx, by in np.unique(pairs[:, :2], axis=0):
        cells = pairs[(pairs[:, 0] == bx) & (pairs[:, 1] == by), 2]
        tri = c_tri[cells].reshape(-1, 3)
        used, local = np.unique(tri.ravel(), return_inverse=True)
        out[(int(bx), int(by))] = (c_pos[used], c_nrm[used], c_col[used], local.reshape(-1, 3))
    return out
