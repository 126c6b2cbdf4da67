"""The ego's route: points every DS metres ahead of it, its traffic lights and speed limits.

:class:`PolylineRoute` is what the following controller reads (projection, look-ahead point, curvature,
the path frame for perceived vehicles, the next light and its state, the speed limit). :class:`LaneRoute`
fills it on a lite map: a chain of lanes chosen at junctions by a seeded draw.
:class:`genesis_rl.sim.carla.route.CarlaRoute` fills it on a ``carla.Map``. The controller reads its route
and the traffic lights from the map (ground truth, as CARLA's BehaviorAgent does through its global route
planner); everything about other vehicles comes from perception.
"""

from __future__ import annotations

import abc
from typing import Any

import numpy as np

from genesis_rl.sim.lite.maps.lane_graph import DS, RoadMap

PLAN_AHEAD = 160.0  # keep at least this much route ahead [m]
CURVATURE_CHORD = 20.0  # the length of road a bend's curvature is measured over [m]
_HALF_CHORD = max(int(CURVATURE_CHORD / (2 * DS)), 1)
#: triangular weights over a chord of samples, summing to 1 (curvature_ahead runs every control step)
_CHORD_WEIGHTS = np.concatenate([np.arange(1, _HALF_CHORD + 1), np.arange(_HALF_CHORD - 1, 0, -1)]).astype(np.float64)
_CHORD_WEIGHTS /= _CHORD_WEIGHTS.sum()
SEARCH_BACK, SEARCH_AHEAD = 20, 80  # projection window around the last index [samples]


class PolylineRoute(abc.ABC):
    """Route points ``xy`` (N, 2) every DS metres and the ego's projection ``index`` on them. Subclasses
    keep at least PLAN_AHEAD metres ahead (``_extend``) and say where the lights and limits are."""

    xy: np.ndarray
    index: int

    @abc.abstractmethod
    def _extend(self) -> None:
        """Append route points until PLAN_AHEAD metres lie ahead of ``index``."""

    @abc.abstractmethod
    def next_signal(self, max_ahead: float) -> tuple[float, Any] | None:
        """Distance along the route to the next signalised stop line within ``max_ahead`` and a reference
        to its light for :meth:`signal_state`; None when there is none."""

    @abc.abstractmethod
    def signal_state(self, ref: Any, time_s: float) -> str:
        """'green', 'yellow' or 'red' for the light ``ref`` at episode time ``time_s`` (plus the scene's offset)."""

    @abc.abstractmethod
    def speed_limit(self) -> float:
        """The speed limit where the ego is [m/s]."""

    @property
    def s(self) -> float:
        """Arc length of the ego's projection on the route [m]."""
        return self.index * DS

    def update(self, x: float, y: float) -> None:
        """Project the ego's position on the route near its last projection (never jumps backwards far)."""
        lo = max(self.index - SEARCH_BACK, 0)
        hi = min(self.index + SEARCH_AHEAD, len(self.xy))
        d2 = np.sum((self.xy[lo:hi] - (x, y)) ** 2, axis=1)
        self.index = lo + int(np.argmin(d2))
        self._extend()

    def point_at(self, s: float) -> np.ndarray:
        i = int(np.clip(round(s / DS), 0, len(self.xy) - 1))
        return self.xy[i]

    def heading_at(self, s: float) -> float:
        i = int(np.clip(round(s / DS), 0, len(self.xy) - 2))
        d = self.xy[i + 1] - self.xy[i]
        return float(np.arctan2(d[1], d[0]))

    def curvature_ahead(self, dist: float) -> float:
        """Largest absolute curvature [1/m] on the next ``dist`` metres: the heading change per metre, averaged
        with triangular weights over a :data:`CURVATURE_CHORD` of road.

        Why so wide: a lane polyline turns at its vertices, not between them. Until 0.18 this was the heading
        change per sample smoothed over 2 m, which read the highway's vertices as bends 3.6x tighter than
        they are (radius ~25 m where the road's is 80-110 m), and the controller slowed from 25 m/s to 11 m/s
        on a clear main line. The triangle spreads vertices a few metres apart evenly (a plain 20 m window
        reads 1.2x too much when it holds three of them); on a smooth arc both give 1/radius."""
        i0 = self.index
        i1 = min(i0 + int(dist / DS), len(self.xy) - 2)
        if i1 - i0 < 4:
            return 0.0
        d = np.diff(self.xy[i0 : i1 + 2], axis=0)
        turn = np.diff(np.unwrap(np.arctan2(d[:, 1], d[:, 0])))  # heading change per sample [rad]
        if len(turn) < len(_CHORD_WEIGHTS):  # less road ahead than a chord: its heading change over its length
            return float(abs(turn.sum()) / (len(turn) * DS))
        return float(np.max(np.abs(np.convolve(turn, _CHORD_WEIGHTS, mode="valid"))) / DS)

    def frame_of(self, points: np.ndarray, max_ahead: float) -> tuple[np.ndarray, np.ndarray]:
        """For world points (M, 2): arc length ahead of the ego along the route and signed lateral offset
        (left positive) from the nearest route point within ``max_ahead``; NaN for points beyond it."""
        i1 = min(self.index + int(max_ahead / DS) + 1, len(self.xy) - 1)
        seg = self.xy[self.index : i1 + 1]
        if len(points) == 0 or len(seg) < 2:
            return np.full(len(points), np.nan), np.full(len(points), np.nan)
        d2 = ((points[:, None, :] - seg[None, :, :]) ** 2).sum(-1)
        k = np.argmin(d2, axis=1)
        k = np.minimum(k, len(seg) - 2)
        t = seg[k + 1] - seg[k]
        t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
        rel = points - seg[k]
        along = k * DS + (rel * t).sum(1)
        lateral = t[:, 0] * rel[:, 1] - t[:, 1] * rel[:, 0]
        beyond = (k >= len(seg) - 2) & (along > max_ahead)
        along = np.where(beyond, np.nan, along)
        return along, np.where(beyond, np.nan, lateral)


class LaneRoute(PolylineRoute):
    """A route on a lite map: points with the lane each came from, lanes drawn at junctions with ``rng``."""

    def __init__(self, road_map: RoadMap, lane: int, s: float, next_lane: int, rng: np.random.Generator) -> None:
        self.map = road_map
        self.rng = rng
        self.lanes: list[int] = []
        self._xy: list[np.ndarray] = []
        self._lane_of: list[np.ndarray] = []
        self.lane_end_s: list[float] = []  # route arc length at the end of each lane in ``lanes``
        self._append(lane)
        if next_lane >= 0:
            self._append(next_lane)
        self._rebuild()
        self.index = int(np.clip(round(s / DS), 0, len(self.xy) - 1))

    def _append(self, lane: int) -> None:
        xy = self.map.lanes[lane].xy
        if self._xy:
            xy = xy[1:]  # a lane starts where its predecessor ends
        self.lanes.append(lane)
        self._xy.append(xy)
        self._lane_of.append(np.full(len(xy), lane))
        total = sum(len(a) for a in self._xy)
        self.lane_end_s.append((total - 1) * DS)

    def _rebuild(self) -> None:
        self.xy = np.concatenate(self._xy)
        self.lane_of = np.concatenate(self._lane_of)

    def _extend(self) -> None:
        while (len(self.xy) - 1 - self.index) * DS < PLAN_AHEAD:
            succ = self.map.lanes[self.lanes[-1]].successors
            self._append(int(succ[int(self.rng.integers(len(succ)))]))
            self._rebuild()

    def next_signal(self, max_ahead: float) -> tuple[float, tuple[int, int]] | None:
        """The next stop line within ``max_ahead`` and its light's (junction, group)."""
        for lane, end_s in zip(self.lanes, self.lane_end_s, strict=True):
            ahead = end_s - self.s
            if ahead < -1.0:
                continue
            if ahead > max_ahead:
                return None
            sig = self.map.lanes[lane].signal
            if sig is not None:
                return ahead, sig
        return None

    def signal_state(self, ref: Any, time_s: float) -> str:
        junction, group = ref
        return self.map.signal_state(junction, group, time_s)

    def speed_limit(self) -> float:
        return self.map.speed_limit(int(self.lane_of[self.index]))
