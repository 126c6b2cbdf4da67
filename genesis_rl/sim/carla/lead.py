"""The vehicle ahead in the ego's path, measured along the lane (ground truth for rules and reports).

The path is the ego's lane ahead from the map's waypoints (straightest branch at junctions, as the lite
backend predicts a path from the current heading); a vehicle is on it when its centre lies within half a
lane of the path. Pure numpy on points, so it is tested without a server.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from genesis_rl.sim.interface import LeadInfo

PATH_STEP = 2.0  # [m] spacing of path points
PATH_LENGTH = 100.0  # [m] how far ahead the lead is looked for


def lane_path(waypoint: Any, length: float = PATH_LENGTH, step: float = PATH_STEP) -> np.ndarray:
    """Points (N, 2) of the lane ahead of ``waypoint`` (CARLA frame), taking the straightest branch."""
    pts = [(waypoint.transform.location.x, waypoint.transform.location.y)]
    wp, travelled = waypoint, 0.0
    while travelled < length:
        nxt = wp.next(step)
        if not nxt:
            break
        yaw = wp.transform.rotation.yaw
        wp = min(nxt, key=lambda w: abs((w.transform.rotation.yaw - yaw + 180.0) % 360.0 - 180.0))
        pts.append((wp.transform.location.x, wp.transform.location.y))
        travelled += step
    return np.asarray(pts, dtype=np.float64)


def path_offset(path: np.ndarray, point: np.ndarray) -> float | None:
    """The distance [m] of ``point`` (x, y) from the polyline ``path`` (None: a path of fewer than 2 points)."""
    if len(path) < 2:
        return None
    seg = np.diff(path, axis=0)
    seg_len2 = np.maximum((seg**2).sum(axis=1), 1e-18)
    rel = np.asarray(point, dtype=np.float64).reshape(1, 2) - path[:-1]
    t = np.clip((rel * seg).sum(axis=1) / seg_len2, 0.0, 1.0)
    return float(np.min(np.linalg.norm(rel - t[:, None] * seg, axis=1)))


def lead_on_path(path: np.ndarray, ego_xy: np.ndarray, ego_half_length: float, others_xy: np.ndarray,
                 others_half_length: np.ndarray, others_speed: np.ndarray, others_id: np.ndarray,
                 lane_half_width: float = 1.75) -> LeadInfo | None:
    """The nearest vehicle whose centre is within ``lane_half_width`` of the path and ahead of the ego;
    the gap is bumper to bumper along the path, floored at 0."""
    if len(path) < 2 or len(others_xy) == 0:
        return None
    seg = np.diff(path, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    s_start = np.concatenate([[0.0], np.cumsum(seg_len)])[:-1]

    def along(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rel = points[:, None, :] - path[None, :-1, :]
        t = np.clip((rel * seg[None]).sum(-1) / np.maximum(seg_len, 1e-9) ** 2, 0.0, 1.0)
        foot = path[None, :-1, :] + t[..., None] * seg[None]
        dist = np.linalg.norm(points[:, None, :] - foot, axis=-1)
        best = dist.argmin(axis=1)
        rows = np.arange(len(points))
        return s_start[best] + t[rows, best] * seg_len[best], dist[rows, best]

    s_ego, _ = along(np.asarray(ego_xy, dtype=np.float64).reshape(1, 2))
    s, lateral = along(np.asarray(others_xy, dtype=np.float64).reshape(-1, 2))
    ahead = (lateral <= lane_half_width) & (s > s_ego[0])
    if not ahead.any():
        return None
    gaps = s - s_ego[0] - ego_half_length - np.asarray(others_half_length, dtype=np.float64)
    j = int(np.flatnonzero(ahead)[np.argmin(gaps[ahead])])
    return LeadInfo(int(others_id[j]), float(max(gaps[j], 0.0)), float(others_speed[j]))
