"""Deterministic scenery placement shared by the maps: keep buildings and trees off the roads."""

from __future__ import annotations

import numpy as np

CELL = 2.0  # occupancy raster cell [m]


class RoadMask:
    """A raster of cells within ``clearance`` metres of any lane or junction, for placing scenery."""

    def __init__(self, lane_xy: np.ndarray, bounds: tuple[float, float, float, float], clearance: float) -> None:
        import cv2  # local: start-up cost (OpenCV, ~0.1 s; only map building needs it)

        self.xmin, self.ymin, xmax, ymax = bounds
        self.nx = int((xmax - self.xmin) / CELL) + 1
        self.ny = int((ymax - self.ymin) / CELL) + 1
        grid = np.zeros((self.ny, self.nx), np.uint8)
        ix, iy = self._cells(lane_xy[:, 0], lane_xy[:, 1])
        ok = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        grid[iy[ok], ix[ok]] = 1
        r = int(np.ceil(clearance / CELL))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        self.grid = cv2.dilate(grid, kernel)

    def _cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.floor((np.asarray(x) - self.xmin) / CELL).astype(int),
            np.floor((np.asarray(y) - self.ymin) / CELL).astype(int),
        )

    def free(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ix, iy = self._cells(x, y)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        out = np.zeros(np.shape(x), bool)
        out[inside] = self.grid[iy[inside], ix[inside]] == 0
        return out


def lane_and_junction_points(lanes: list, junctions: list) -> np.ndarray:
    pts = [ln.xy for ln in lanes]
    for j in junctions:
        a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        r = np.linspace(0, j.radius, 6)[:, None]
        ring = np.column_stack([(j.center[0] + r * np.cos(a)).ravel(), (j.center[1] + r * np.sin(a)).ravel()])
        pts.append(ring)
    return np.vstack(pts)


def grid_network(n: int, spacing: float, lanes_each_way: int) -> tuple[dict, list]:
    """Nodes ``i * n + j`` at (i, j) * spacing and the roads between grid neighbours (a street grid)."""
    nodes = {i * n + j: (i * spacing, j * spacing) for i in range(n) for j in range(n)}
    roads: list = []
    for i in range(n):
        for j in range(n):
            if i + 1 < n:
                roads.append((i * n + j, (i + 1) * n + j, [], lanes_each_way))
            if j + 1 < n:
                roads.append((i * n + j, i * n + j + 1, [], lanes_each_way))
    return nodes, roads


def overlaps_any(occupied: np.ndarray, x: float, y: float, w: float, d: float, margin: float) -> bool:
    """Whether an axis-aligned w x d rectangle at (x, y) comes within ``margin`` of any placed one
    (rows of ``occupied``: x, y, w, d). A point is a 0 x 0 rectangle."""
    return bool(
        len(occupied)
        and np.any(
            (np.abs(occupied[:, 0] - x) < (occupied[:, 2] + w) / 2 + margin)
            & (np.abs(occupied[:, 1] - y) < (occupied[:, 3] + d) / 2 + margin)
        )
    )
