"""A lane graph built from a road network: roads between nodes, junctions with connector lanes and signals.

Every lane is a polyline resampled at a uniform spacing ``DS`` so that traffic can look points up by integer
index, vectorised over all vehicles. All lanes' points live in one concatenated array (``RoadMap.points``);
lane ``i`` occupies ``offset[i] : offset[i] + count[i]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from genesis_rl.sim.spacing import DS  # shared with the CARLA backend's routes

GRID_CELL = 25.0  # spatial hash cell for nearest-lane queries [m]
_MAX_RINGS = 6  # beyond ~150 m from every lane the nearest-lane search scans the whole map
LANE_WIDTH = 3.5  # [m]

Elevation = Callable[[np.ndarray, np.ndarray], np.ndarray]


def flat(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.zeros_like(np.asarray(x, dtype=np.float64))


@dataclass
class Lane:
    """A directed lane. ``road`` is the road it belongs to (-1 for a junction connector); ``index`` counts
    lanes from the centre line outward (0 = innermost / fast lane)."""

    id: int
    road: int
    junction: int
    index: int
    xy: np.ndarray  # (N, 2)
    successors: list[int] = field(default_factory=list)
    left: int = -1  # neighbouring lane, same direction, toward the centre line
    right: int = -1  # neighbouring lane, same direction, toward the kerb
    signal: tuple[int, int] | None = None  # (junction, phase group) of the light at this lane's end

    @property
    def length(self) -> float:
        return (len(self.xy) - 1) * DS


@dataclass
class Road:
    """A two-way road between two nodes: centre line (trimmed at junctions) and lanes per direction."""

    id: int
    node_a: int
    node_b: int
    centerline: np.ndarray  # (N, 2), from node_a's junction edge to node_b's
    lanes_each_way: int
    forward_lanes: list[int] = field(default_factory=list)  # a -> b, index 0..n-1
    backward_lanes: list[int] = field(default_factory=list)  # b -> a

    @property
    def width(self) -> float:
        return 2 * self.lanes_each_way * LANE_WIDTH


@dataclass
class Junction:
    id: int
    node: int
    center: np.ndarray  # (2,)
    radius: float
    signalised: bool
    roads: list[int] = field(default_factory=list)
    #: signal heads: (position xy, heading the head faces, phase group)
    signal_heads: list[tuple[np.ndarray, float, int]] = field(default_factory=list)


@dataclass(frozen=True)
class SignalTiming:
    """Fixed-time two-phase plan: group 0 green, yellow, all red, then group 1 the same. Seconds."""

    green: float = 12.0
    yellow: float = 3.0
    all_red: float = 1.5

    @property
    def cycle(self) -> float:
        return 2 * (self.green + self.yellow + self.all_red)

    def state(self, t: float, group: int) -> str:
        """'green', 'yellow' or 'red' for ``group`` at time ``t`` (s)."""
        half = self.green + self.yellow + self.all_red
        u = (t + (half if group == 1 else 0.0)) % self.cycle
        if u < self.green:
            return "green"
        if u < self.green + self.yellow:
            return "yellow"
        return "red"


@dataclass(frozen=True)
class Building:
    x: float
    y: float
    yaw: float
    width: float
    depth: float
    height: float
    color: tuple[float, float, float]


@dataclass(frozen=True)
class Tree:
    x: float
    y: float
    height: float
    kind: str  # "pine" or "broadleaf"


@dataclass
class RoadMap:
    """Lanes + roads + junctions + scenery of one map, with flat arrays for vectorised look-ups."""

    #: never changed by an episode, so a snapshot of one shares it (``core.state_copy``)
    SNAPSHOT_SHARED: ClassVar[bool] = True
    name: str
    lanes: list[Lane]
    roads: list[Road]
    junctions: list[Junction]
    elevation: Elevation
    buildings: list[Building]
    trees: list[Tree]
    bounds: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax of the ground
    ground_color: tuple[float, float, float]
    timing: SignalTiming = field(default_factory=SignalTiming)
    #: per-junction offset of the signal plan (s); deterministic per map
    signal_offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # flat arrays, filled by finalize()
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # x, y, z
    headings: np.ndarray = field(default_factory=lambda: np.zeros(0))
    slopes: np.ndarray = field(default_factory=lambda: np.zeros(0))  # pitch angle (rad)
    offset: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    count: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    point_lane: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    _grid: dict | None = field(default=None, repr=False)
    _grid_span: tuple[int, int, int, int] | None = field(default=None, repr=False)

    def finalize(self) -> RoadMap:
        xy = np.concatenate([ln.xy for ln in self.lanes])
        z = self.elevation(xy[:, 0], xy[:, 1])
        self.points = np.column_stack([xy, z])
        self.count = np.array([len(ln.xy) for ln in self.lanes], dtype=np.int64)
        self.offset = np.concatenate([[0], np.cumsum(self.count)[:-1]]).astype(np.int64)
        self.length = (self.count - 1) * DS
        self.point_lane = np.repeat(np.arange(len(self.lanes)), self.count)
        heads, slopes = [], []
        for ln, off, n in zip(self.lanes, self.offset, self.count, strict=True):
            p = self.points[off : off + n]
            d = np.diff(p, axis=0)
            d = np.vstack([d, d[-1:]])
            heads.append(np.arctan2(d[:, 1], d[:, 0]))
            slopes.append(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
            assert ln.successors, f"lane {ln.id} has no successor"
        self.headings = np.concatenate(heads)
        self.slopes = np.concatenate(slopes)
        if len(self.signal_offsets) != len(self.junctions):
            self.signal_offsets = np.array([(j.id * 7.3) % self.timing.cycle for j in self.junctions])
        return self

    # -- queries ---------------------------------------------------------------------------------------
    def point_index(self, lane: int | np.ndarray, s: float | np.ndarray) -> np.ndarray:
        """Flat index of the sample at arc length ``s`` on ``lane`` (clipped to the lane)."""
        lane = np.asarray(lane)
        i = np.clip(np.rint(np.asarray(s) / DS).astype(np.int64), 0, self.count[lane] - 1)
        return self.offset[lane] + i

    def pose(self, lane: int, s: float) -> tuple[float, float, float, float]:
        """x, y, z, heading at arc length ``s`` on ``lane``."""
        # point_index's arithmetic on Python scalars (round() rounds half to even like np.rint): scene generation
        # asks this for every vehicle it tries, and numpy's per-call overhead was most of its cost
        lane = int(lane)
        i = int(self.offset[lane]) + min(max(int(round(float(s) / DS)), 0), int(self.count[lane]) - 1)
        x, y, z = self.points[i]
        return float(x), float(y), float(z), float(self.headings[i])

    def signal_state(self, junction: int, group: int, t: float) -> str:
        return self.timing.state(t + float(self.signal_offsets[junction]), group)

    def speed_limit(self, lane: int) -> float:
        """Speed limit [m/s]: highway lanes (3 each way) allow 25 m/s, town streets and junctions 12 m/s."""
        road = self.lanes[lane].road
        return 25.0 if road >= 0 and self.roads[road].lanes_each_way >= 3 else 12.0

    def driving_lanes(self) -> list[int]:
        """Lanes on roads (not junction connectors): where vehicles are spawned."""
        return [ln.id for ln in self.lanes if ln.road >= 0]

    def nearest_lane_point(self, x: float, y: float, heading: float | None = None) -> int:
        """Flat index of the lane sample nearest to (x, y), optionally among headings within 60 degrees:
        exactly the sample a scan of the whole map finds (ties to the lowest index), searched in square
        rings of spatial-hash cells outward from the point's cell. A sample in ring r + 1 or farther is at
        least r cells away, so the search stops once the best is nearer than that. (A whole-map scan cost
        1 ms a step for an ego driven off the road.)"""
        if self._grid is None:
            self._build_grid()
        assert self._grid is not None and self._grid_span is not None
        cx, cy = int(np.floor(x / GRID_CELL)), int(np.floor(y / GRID_CELL))
        kx0, ky0, kx1, ky1 = self._grid_span
        near_map = kx0 - _MAX_RINGS <= cx <= kx1 + _MAX_RINGS and ky0 - _MAX_RINGS <= cy <= ky1 + _MAX_RINGS
        cands: list[np.ndarray] = []
        dists: list[np.ndarray] = []
        best_d2 = np.inf
        for r in range(_MAX_RINGS if near_map else 0):  # far outside the map no ring can hold a lane
            ring = [(cx + i, cy + j) for i in range(-r, r + 1) for j in range(-r, r + 1) if max(abs(i), abs(j)) == r]
            found = [self._grid[k] for k in ring if k in self._grid]
            if found:
                cands.append(np.concatenate(found))
                dists.append(self._distances2(cands[-1], x, y, heading))
                best_d2 = min(best_d2, float(dists[-1].min()))
            if best_d2 < (r * GRID_CELL) ** 2:
                cand, d2 = np.concatenate(cands), np.concatenate(dists)
                return int(cand[d2 == best_d2].min())
        best = self._nearest_among(np.arange(len(self.points)), x, y, heading)
        return max(best, 0)

    def _build_grid(self) -> None:
        """The spatial hash: lane-sample indices per GRID_CELL cell, ascending within a cell, and the span
        of occupied cells."""
        keys = np.floor(self.points[:, :2] / GRID_CELL).astype(np.int64)
        order = np.lexsort((keys[:, 1], keys[:, 0]))
        grid: dict[tuple[int, int], list[int]] = {}
        for k, idx in zip(map(tuple, keys[order]), order, strict=True):
            grid.setdefault(k, []).append(int(idx))
        self._grid = {k: np.array(v) for k, v in grid.items()}
        self._grid_span = (*keys.min(axis=0).tolist(), *keys.max(axis=0).tolist())

    def _distances2(self, cand: np.ndarray, x: float, y: float, heading: float | None) -> np.ndarray:
        """Squared distances from (x, y) to the samples ``cand``; inf where the heading differs by >= 60 deg."""
        d2 = (self.points[cand, 0] - x) ** 2 + (self.points[cand, 1] - y) ** 2
        if heading is not None:
            d2 = np.where(np.cos(self.headings[cand] - heading) > 0.5, d2, np.inf)
        return d2

    def _nearest_among(self, cand: np.ndarray, x: float, y: float, heading: float | None) -> int:
        d2 = self._distances2(cand, x, y, heading)
        k = int(np.argmin(d2))
        return int(cand[k]) if np.isfinite(d2[k]) else -1


# --- construction -------------------------------------------------------------------------------------


def resample(poly: np.ndarray, ds: float = DS) -> np.ndarray:
    """Resample a polyline at uniform arc-length spacing ``ds`` (last point kept; length rounded)."""
    seg = np.hypot(*np.diff(poly, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(round(s[-1] / ds)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])])


def smooth_path(ctrl: np.ndarray, samples_per_seg: int = 24) -> np.ndarray:
    """Centripetal Catmull-Rom spline through control points (for curvy roads)."""
    if len(ctrl) < 3:
        return ctrl.astype(np.float64)
    p = np.vstack([2 * ctrl[0] - ctrl[1], ctrl, 2 * ctrl[-1] - ctrl[-2]])
    out = []
    for i in range(1, len(p) - 2):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        t = np.linspace(0, 1, samples_per_seg, endpoint=False)[:, None]
        out.append(
            0.5
            * (
                2 * p1
                + (-p0 + p2) * t
                + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
                + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3
            )
        )
    out.append(ctrl[-1:])
    return np.vstack(out)


def _normals(poly: np.ndarray) -> np.ndarray:
    """Right-hand unit normals of a polyline (x east, y north: right of heading h is (sin h, -cos h))."""
    d = np.gradient(poly, axis=0)
    h = np.arctan2(d[:, 1], d[:, 0])
    return np.column_stack([np.sin(h), -np.cos(h)])


def _trim(poly: np.ndarray, start: float, end: float) -> np.ndarray:
    seg = np.hypot(*np.diff(poly, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = (s >= start) & (s <= s[-1] - end)
    out = poly[keep]
    if len(out) < 2:
        raise ValueError("road too short for its junctions")
    return out


def _bezier(p0: np.ndarray, h0: float, p1: np.ndarray, h1: float) -> np.ndarray:
    d = float(np.hypot(*(p1 - p0)))
    k = d * 0.42
    c0 = p0 + k * np.array([math.cos(h0), math.sin(h0)])
    c1 = p1 - k * np.array([math.cos(h1), math.sin(h1)])
    t = np.linspace(0, 1, max(8, int(d / 0.25)))[:, None]
    return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c0 + 3 * (1 - t) * t**2 * c1 + t**3 * p1


@dataclass
class NetworkSpec:
    """Nodes (id -> xy), roads (node a, node b, intermediate control points, lanes each way) and
    per-node junction radius; nodes of degree >= 3 get traffic lights unless listed in ``unsignalised``."""

    nodes: dict[int, tuple[float, float]]
    roads: Sequence[tuple[int, int, Sequence[tuple[float, float]], int]]
    junction_radius: dict[int, float]
    unsignalised: set[int] = field(default_factory=set)


def build_network(spec: NetworkSpec) -> tuple[list[Lane], list[Road], list[Junction]]:
    lanes: list[Lane] = []
    roads: list[Road] = []
    node_roads: dict[int, list[int]] = {n: [] for n in spec.nodes}

    for rid, (a, b, ctrl, n_lanes) in enumerate(spec.roads):
        pts = np.array([spec.nodes[a], *ctrl, spec.nodes[b]], dtype=np.float64)
        path = smooth_path(pts) if len(pts) > 2 else pts
        path = resample(path, 0.25)
        path = _trim(path, spec.junction_radius[a], spec.junction_radius[b])
        center = resample(path)
        road = Road(rid, a, b, center, n_lanes)
        nrm = _normals(center)
        for k in range(n_lanes):
            off = (k + 0.5) * LANE_WIDTH
            fwd = resample(center + nrm * off)
            bwd = resample((center - nrm * off)[::-1])
            for xy, bucket in ((fwd, road.forward_lanes), (bwd, road.backward_lanes)):
                lane = Lane(len(lanes), rid, -1, k, xy)
                lanes.append(lane)
                bucket.append(lane.id)
        for side in (road.forward_lanes, road.backward_lanes):
            for k, lid in enumerate(side):
                lanes[lid].left = side[k - 1] if k > 0 else -1
                lanes[lid].right = side[k + 1] if k + 1 < len(side) else -1
        roads.append(road)
        node_roads[a].append(rid)
        node_roads[b].append(rid)

    junctions: list[Junction] = []
    for node, rids in node_roads.items():
        jid = len(junctions)
        signalised = len(rids) >= 3 and node not in spec.unsignalised
        junc = Junction(jid, node, np.array(spec.nodes[node], float), spec.junction_radius[node], signalised, rids)
        junctions.append(junc)
        # incoming / outgoing lanes of each road at this node
        incoming: list[tuple[int, list[int]]] = []
        outgoing: list[tuple[int, list[int]]] = []
        for rid in rids:
            road = roads[rid]
            if road.node_b == node:
                incoming.append((rid, road.forward_lanes))
                outgoing.append((rid, road.backward_lanes))
            if road.node_a == node:
                incoming.append((rid, road.backward_lanes))
                outgoing.append((rid, road.forward_lanes))
        # phase groups: roads whose axis is near the first incoming road's axis share group 0
        axis0 = None
        for rid_in, in_lanes in incoming:
            end = lanes[in_lanes[0]].xy
            h_in = math.atan2(*(end[-1] - end[-2])[::-1])
            if axis0 is None:
                axis0 = h_in
            group = 0 if abs(math.sin(h_in - axis0)) < 0.7 else 1
            for out_rid, out_lanes in outgoing:
                if out_rid == rid_in and len(rids) > 1:
                    continue  # no U-turns
                start = lanes[out_lanes[0]].xy
                h_out = math.atan2(*(start[1] - start[0])[::-1])
                turn = math.atan2(math.sin(h_out - h_in), math.cos(h_out - h_in))
                n_in, n_out = len(in_lanes), len(out_lanes)
                pairs: list[tuple[int, int]]
                if abs(turn) < math.radians(35):
                    pairs = [(k, min(k, n_out - 1)) for k in range(n_in)]
                elif turn > 0:  # left turn from the inner lane
                    pairs = [(0, 0)]
                else:  # right turn from the outer lane
                    pairs = [(n_in - 1, n_out - 1)]
                if len(rids) == 2:  # a bend, not a junction: every lane continues
                    pairs = [(k, min(k, n_out - 1)) for k in range(n_in)]
                for k_in, k_out in pairs:
                    lin, lout = lanes[in_lanes[k_in]], lanes[out_lanes[k_out]]
                    p0, p1 = lin.xy[-1], lout.xy[0]
                    h0 = math.atan2(*(lin.xy[-1] - lin.xy[-2])[::-1])
                    h1 = math.atan2(*(lout.xy[1] - lout.xy[0])[::-1])
                    conn = Lane(len(lanes), -1, jid, k_in, resample(_bezier(p0, h0, p1, h1)), [lout.id])
                    lanes.append(conn)
                    lin.successors.append(conn.id)
                    if signalised:
                        lin.signal = (jid, group)
            if signalised:
                # a signal head on the kerb side, just before the stop line, facing the traffic
                outer = lanes[in_lanes[-1]].xy
                h = math.atan2(*(outer[-1] - outer[-2])[::-1])
                pos = outer[-1] + np.array([math.sin(h), -math.cos(h)]) * (LANE_WIDTH * 0.5 + 1.2)
                junc.signal_heads.append((pos, h + math.pi, group))
    for ln in lanes:
        if not ln.successors:
            raise ValueError(f"lane {ln.id} on road {ln.road} has no successor (dead end)")
    return lanes, roads, junctions
