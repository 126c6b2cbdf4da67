"""The built-in controller's route on a ``carla.Map``: a global plan to a destination, as BehaviorAgent's.

CARLA's BehaviorAgent plans with its GlobalRoutePlanner: a graph of the map's topology (lane segments
joined where one flows into the next, and side by side where a lane change is allowed), A* to a
destination, and a dense path of waypoints with road options (follow, turn at a junction, change lane).
:class:`RoutePlanner` builds that graph from ``carla_map.get_topology()`` with networkx, and
:class:`CarlaRoute` keeps the controller's :class:`~genesis_rl.sim.route.PolylineRoute` interface filled
ahead of the ego: it draws a destination with the episode's seeded generator, plans to it, samples the
lanes every :data:`~genesis_rl.sim.spacing.DS` metres, and draws the next destination when the plan runs
short, so the ego roams as long as the episode lasts.

Lane changes are decided per waypoint, as CARLA's planner decides them (``_lane_change_link``): a section
has a lane-change edge when the marking allows the change at any of its waypoints, and the route changes at
the first waypoint from where it stands that allows it, blending over at most :data:`LANE_CHANGE_LENGTH` of
waypoints that all allow it (a marking that forbids changing halfway ends the blend there).

Everything here reads only the map (``carla.Map``: it works on a map built from OpenDRIVE text without a
server). The traffic lights are the map's signal landmarks of type 1000001 on the route's lanes; their
state comes from a callable (a server's ``carla.TrafficLight`` states, or a fixed plan offline), as the
lite controller reads its map's signal plan. Speed limits are the OpenDRIVE ``<type><speed>`` of each road.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import networkx as nx
import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.carla._carla import require_carla
from genesis_rl.sim.carla.lanes import lane_from_key
from genesis_rl.sim.route import PLAN_AHEAD, PolylineRoute
from genesis_rl.sim.spacing import DS

LANE_CHANGE_LENGTH = 20.0  # [m] a lane change blends from one lane centre to the next over this distance
LANE_CHANGE_COST = 30.0  # [m] the planner's extra cost of a lane change (prefers staying in lane)
DESTINATION_RANGE = (300.0, 1500.0)  # [m] route length to a drawn destination
DEFAULT_SPEED_LIMIT = 30.0 / 3.6  # [m/s] CARLA's limit where the map gives none
SIGNAL_TYPE = "1000001"

#: (landmark, time [s]) -> 'red', 'yellow', 'green' (or 'off'/'unknown': treated as green)
SignalState = Callable[[Any, float], str]


@dataclass(frozen=True)
class Segment:
    """One lane of one road section, from the topology: entry and exit waypoints, length along the lane."""

    index: int
    key: tuple[int, int, int]  # road id, section id, lane id
    entry: Any
    exit: Any
    length: float
    junction: bool


def _key(wp: Any) -> tuple[int, int, int]:
    return (int(wp.road_id), int(wp.section_id), int(wp.lane_id))


def speed_limits(xodr: str) -> dict[int, float]:
    """Road id -> the first ``<type><speed max>`` of the road [m/s] (km/h, mph and m/s units)."""
    factor = {"km/h": 1 / 3.6, "mph": 0.44704, "m/s": 1.0}
    out: dict[int, float] = {}
    for road in ET.fromstring(xodr).iter("road"):
        speed = road.find("type/speed")
        if speed is not None and speed.get("max") not in (None, "", "no limit", "undefined"):
            try:
                unit = factor.get(speed.get("unit", "m/s"), 1.0)
                out[int(road.get("id", "-1"))] = float(speed.get("max", "0")) * unit
            except ValueError:
                continue
    return out


class RoutePlanner:
    """The topology graph of a ``carla.Map``: follow edges (one lane flows into the next) and lane-change
    edges (same road, same direction, driving lanes side by side, where the marking at some waypoint of the
    section allows the change: ``waypoint.lane_change``, read at every waypoint)."""

    def __init__(self, carla_map: Any) -> None:
        require_carla()
        self.map = carla_map
        self.segments: list[Segment] = []
        self.by_key: dict[tuple[int, int, int], int] = {}
        follows: list[tuple[tuple[int, int, int], tuple[int, int, int]]] = []
        # get_topology() pairs each lane section's start with the start of each lane it flows into (or with
        # its own end where it flows nowhere)
        samples: dict[int, list[Any]] = {}
        for entry, nxt in carla_map.get_topology():
            key = _key(entry)
            if key not in self.by_key:
                samples[len(self.segments)] = _samples(entry)
                end = samples[len(self.segments)][-1]
                self.by_key[key] = len(self.segments)
                self.segments.append(Segment(len(self.segments), key, entry, end, max(abs(end.s - entry.s), DS),
                                             bool(entry.is_junction)))
            if _key(nxt) != key:
                follows.append((key, _key(nxt)))
        g = nx.DiGraph()
        for seg in self.segments:
            g.add_node(seg.index)
        for a, b in follows:
            if b in self.by_key:
                j = self.by_key[b]
                g.add_edge(self.by_key[a], j, weight=self.segments[j].length, kind="follow")
        for seg in self.segments:
            if seg.junction:
                continue
            for side in ("left", "right"):
                first = _first_change(samples[seg.index], side)
                side_seg = self.by_key.get(_key(first[1])) if first is not None else None
                if side_seg is not None:
                    cost = self.segments[side_seg].length + LANE_CHANGE_COST
                    g.add_edge(seg.index, side_seg, weight=cost, kind=side)
        self.graph = g

    def segment_of(self, wp: Any) -> int:
        key = _key(wp)
        if key not in self.by_key:
            raise UserInputError(f"the waypoint on road {key[0]}, section {key[1]}, lane {key[2]} is on no lane of "
                                 "the map's topology")
        return self.by_key[key]

    def plan(self, start: int, rng: np.random.Generator, here: Any = None) -> list[tuple[int, str]]:
        """Segments from ``start`` to a destination drawn with ``rng`` among those whose shortest route is
        within :data:`DESTINATION_RANGE` (the farthest reachable one when none is), each with how it is
        entered ('start', 'follow', 'left', 'right'). ``here`` (a waypoint of ``start``): a lane change out of
        ``start`` is planned only where the marking allows one from there on."""
        graph = self.graph
        if here is not None:
            ahead = _samples(here)
            blocked = {(start, b) for b in self.graph.successors(start)
                       if self.graph.edges[start, b]["kind"] != "follow"
                       and _first_change(ahead, self.graph.edges[start, b]["kind"]) is None}
            if blocked:
                graph = nx.restricted_view(self.graph, [], list(blocked))
        dist = nx.single_source_dijkstra_path_length(graph, start, weight="weight")
        lo, hi = DESTINATION_RANGE
        targets = sorted(i for i, d in dist.items() if lo <= d <= hi and not self.segments[i].junction)
        if targets:
            goal = targets[int(rng.integers(len(targets)))]
        else:
            goal = max(dist, key=lambda i: (dist[i], -i))
        if goal == start:
            succ = sorted(graph.successors(start))
            if not succ:
                raise UserInputError(f"lane {self.segments[start].key} of the CARLA map leads nowhere (a dead end)")
            goal = succ[int(rng.integers(len(succ)))]
        path = nx.dijkstra_path(graph, start, goal, weight="weight")
        steps = [(b, graph.edges[a, b]["kind"]) for a, b in zip(path, path[1:], strict=False)]
        if steps and steps[-1][1] != "follow":
            # a leg never ends on a lane change: the next leg would start at the section's end, with no road
            # left to blend over. Go on into a lane that follows.
            end = path[-1]
            onward = sorted(b for b in self.graph.successors(end) if self.graph.edges[end, b]["kind"] == "follow")
            if onward:
                steps.append((onward[int(rng.integers(len(onward)))], "follow"))
        return [(path[0], "start"), *steps]


def _xy(wp: Any) -> tuple[float, float]:
    """A waypoint's position in GENESIS-RL's right-handed frame (CARLA's y negated)."""
    loc = wp.transform.location
    return (float(loc.x), -float(loc.y))


def _samples(wp: Any) -> list[Any]:
    """Waypoints every DS from ``wp`` to the end of its lane section (``wp`` first)."""
    out = [wp]
    try:
        out.extend(w for w in wp.next_until_lane_end(DS) if _key(w) == _key(wp))
    except RuntimeError:  # the client refuses when wp already stands at the lane's end
        pass
    return out


def _change_target(wp: Any, side: str) -> Any:
    """The neighbour waypoint that ``wp``'s marking allows changing into on ``side`` (a driving lane of the
    same road, same direction), or None: CARLA's planner's test, at one waypoint."""
    carla = require_carla()
    if not wp.lane_change & (carla.LaneChange.Left if side == "left" else carla.LaneChange.Right):
        return None
    nb = wp.get_left_lane() if side == "left" else wp.get_right_lane()
    if (nb is None or nb.lane_type != carla.LaneType.Driving or nb.lane_id * wp.lane_id <= 0
            or nb.road_id != wp.road_id):
        return None
    return nb


def _first_change(wps: list[Any], side: str) -> tuple[int, Any] | None:
    """(index, neighbour) of the first of ``wps`` whose marking allows the change to ``side``, or None."""
    for k, w in enumerate(wps):
        nb = _change_target(w, side)
        if nb is not None:
            return k, nb
    return None


def _next_on_lane(wp: Any) -> Any:
    """The waypoint DS further on ``wp``'s lane section, or None at its end."""
    nxt = [w for w in wp.next(DS) if _key(w) == _key(wp)]
    return nxt[0] if nxt else None


@dataclass
class _Stop:
    """A traffic light on the route: route arc length of its stop line, and the landmark."""

    s: float
    landmark: Any


class CarlaRoute(PolylineRoute):
    """The controller's route on a ``carla.Map``, planned as BehaviorAgent plans (see the module doc)."""

    def __init__(self, carla_map: Any, start: Any, rng: np.random.Generator, signal_state: SignalState | None = None,
                 planner: RoutePlanner | None = None, limits: dict[int, float] | None = None) -> None:
        self.planner = planner or RoutePlanner(carla_map)
        self.rng = rng
        self._signal_state = signal_state
        self._limits = limits if limits is not None else speed_limits(carla_map.to_opendrive())
        self._lights = self._index_lights(carla_map)
        self._points: list[tuple[float, float]] = []  # every DS metres along the route
        self._road_of: list[int] = []
        self.options: list[str] = []  # road option per route point: follow, left, right, junction
        self.stops: list[_Stop] = []
        self._last_wp = start
        self._segment = self.planner.segment_of(start)
        self._pending: Any = start  # where the current segment's samples still start (None: all taken)
        self.index = 0
        self.xy = np.zeros((0, 2))
        self._plan_more()

    # -- planning --------------------------------------------------------------------------------------
    @staticmethod
    def _index_lights(carla_map: Any) -> dict[tuple[int, int], list[Any]]:
        """(road id, lane id) -> the traffic-light landmarks valid for that lane."""
        out: dict[tuple[int, int], list[Any]] = {}
        for lm in carla_map.get_all_landmarks_of_type(SIGNAL_TYPE):
            for lo, hi in lm.get_lane_validities():
                for lane in range(min(lo, hi), max(lo, hi) + 1):
                    if lane != 0:
                        out.setdefault((int(lm.road_id), lane), []).append(lm)
        return out

    def _add(self, raw: list[tuple[float, float]], roads: list[int], options: list[str],
             lights: list[tuple[int, Any]] | None = None) -> None:
        """Append the polyline ``raw`` resampled every DS from the route's last point (lanes end at any s,
        and a lane's centre is longer than its road's s on the outside of a bend: the route's index times
        DS stays its arc length). ``lights`` are (raw index, landmark) of stop lines on it."""
        lights = lights or []
        pts = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
        if self._points:
            pts = np.vstack([self._points[-1], pts])
            roads, options = [self._road_of[-1], *roads], [self.options[-1], *options]
            lights = [(k + 1, lm) for k, lm in lights]
        keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-6])
        idx = np.flatnonzero(keep)
        pts = pts[idx]
        if len(pts) < 2:
            if not self._points and len(pts) == 1:
                self._points.append((float(pts[0, 0]), float(pts[0, 1])))
                self._road_of.append(roads[0])
                self.options.append(options[0])
                self._rebuild()
            return
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        base = len(self._points) - (1 if self._points else 0)  # route index of pts[0]
        n = int(round(arc[-1] / DS))
        if n < 1:
            return
        t = np.linspace(0.0, arc[-1], n + 1)
        x, y = np.interp(t, arc, pts[:, 0]), np.interp(t, arc, pts[:, 1])
        nearest = idx[np.clip(np.searchsorted(arc, t), 0, len(arc) - 1)]
        for k in range(1 if self._points else 0, n + 1):
            self._points.append((float(x[k]), float(y[k])))
            self._road_of.append(roads[int(nearest[k])])
            self.options.append(options[int(nearest[k])])
        for j, lm in lights:
            m = int(np.clip(np.searchsorted(idx, j), 0, len(idx) - 1))
            at = base * DS + float(arc[m])
            if not any(stop.landmark.id == lm.id and abs(stop.s - at) < 5.0 for stop in self.stops[-2:]):
                self.stops.append(_Stop(at, lm))  # a lane change and the lane after it can both hold its line
        self._rebuild()

    def _lights_on(self, wps: list[Any]) -> list[tuple[int, Any]]:
        """(index of the nearest sample, landmark) of the lights of ``wps``' lane whose s lies within them."""
        s0, s1 = wps[0].s, wps[-1].s
        return [(int(np.argmin([abs(w.s - lm.s) for w in wps])), lm)
                for lm in self._lights.get((int(wps[0].road_id), int(wps[0].lane_id)), [])
                if min(s0, s1) - 1e-6 <= lm.s <= max(s0, s1) + 1e-6]

    def _append(self, wps: list[Any], option: str) -> None:
        """Add lane samples; note the lights of their lane whose s lies within them."""
        if not wps:
            return
        self._last_wp = wps[-1]
        self._add([_xy(w) for w in wps], [int(w.road_id) for w in wps],
                  ["junction" if w.is_junction and option == "follow" else option for w in wps], self._lights_on(wps))

    def _rebuild(self) -> None:
        self.xy = np.asarray(self._points, dtype=np.float64).reshape(-1, 2)

    def _lights_along(self, pairs: list[tuple[Any, Any]]) -> list[tuple[int, Any]]:
        """(sample index, landmark) of the stop lines within a lane change's samples, on the lane it leaves or
        the lane it enters (each light once): the change often ends at the section's end, at the stop line."""
        if not pairs:
            return []
        found: dict[Any, tuple[int, Any]] = {}
        for lane_of in (1, 0):  # the lane entered first: its light is the one the ego meets
            for k, lm in self._lights_on([p[lane_of] for p in pairs]):
                found.setdefault(lm.id, (k, lm))
        return sorted(found.values(), key=lambda t: t[0])

    def _change_lane(self, side: str) -> Any:
        """Blend from the current lane (where the marking allows the change) into its ``side`` neighbour
        over the next LANE_CHANGE_LENGTH, or over fewer waypoints where the marking forbids changing sooner
        or the section ends, and return the neighbour's waypoint where the blend ends."""
        here = self._last_wp
        n = max(int(LANE_CHANGE_LENGTH / DS), 1)
        ahead = []
        for w in _samples(here)[1 : n + 1]:
            if _change_target(w, side) is None:
                break
            ahead.append(w)
        raw, roads, landed, pairs = [], [], None, []
        for k, w in enumerate(ahead):
            nb = _change_target(w, side)
            a = (k + 1) / len(ahead)
            (x0, y0), (x1, y1) = _xy(w), _xy(nb)
            raw.append(((1 - a) * x0 + a * x1, (1 - a) * y0 + a * y1))
            roads.append(int(w.road_id))
            pairs.append((w, nb))
            landed = nb
        if landed is None:  # the marking allows it here only (or the section ends): step across at this s
            landed = _change_target(here, side) or (here.get_left_lane() if side == "left" else here.get_right_lane())
            raw, roads, pairs = [_xy(landed)], [int(landed.road_id)], [(here, landed)]
        self._add(raw, roads, [side] * len(raw), self._lights_along(pairs))
        self._last_wp = landed
        return landed

    def _emit(self, wp: Any, change_next: str | None, drop_first: bool) -> bool:
        """Sample the section from ``wp`` on; when a lane change follows, stop at the first waypoint whose
        marking allows it, where its blend starts. False (nothing added) when none from ``wp`` on does."""
        samples = _samples(wp)[1 if drop_first else 0 :]
        if change_next is not None:
            first = _first_change(samples, change_next)
            if first is None:
                return False
            samples = samples[: first[0] + 1]
        self._append(samples, "follow")
        return True

    def _plan_more(self) -> None:
        """Plan legs to drawn destinations until PLAN_AHEAD metres lie ahead. The last segment of a leg is
        left pending, so the next leg can change lanes out of it."""
        while (len(self._points) - 1 - self.index) * DS < PLAN_AHEAD:
            before = len(self._points)
            here = self._pending if self._pending is not None else self._last_wp
            steps = self.planner.plan(self._segment, self.rng, here)
            for k, (seg, kind) in enumerate(steps):
                last = k == len(steps) - 1
                following = steps[k + 1][1] if not last else "follow"
                change_next = following if following in ("left", "right") else None
                if kind == "start":
                    wp, drop = self._pending, False
                elif kind == "follow":
                    wp, drop = self.planner.segments[seg].entry, False
                else:
                    wp, drop = self._change_lane(kind), True
                self._segment = seg
                if last:
                    self._pending = wp if not drop else _next_on_lane(wp)
                    break
                self._pending = None
                if wp is not None and not self._emit(wp, change_next, drop):
                    # past every waypoint that allows the next change (it lands mid-section after another
                    # change): plan again from here, where the planner leaves that change out
                    self._pending = wp if not drop else _next_on_lane(wp)
                    break
            if len(self._points) == before and self._pending is None:
                key = self.planner.segments[self._segment].key
                raise UserInputError(f"the route planner found no way on from lane {key}")

    def _extend(self) -> None:
        self._plan_more()

    # -- what the controller reads ---------------------------------------------------------------------
    def next_signal(self, max_ahead: float) -> tuple[float, Any] | None:
        for stop in self.stops:
            ahead = stop.s - self.s
            if ahead < -1.0:
                continue
            return (ahead, stop.landmark) if ahead <= max_ahead else None
        return None

    def signal_state(self, ref: Any, time_s: float) -> str:
        return "green" if self._signal_state is None else self._signal_state(ref, time_s)

    def speed_limit(self) -> float:
        road = self._road_of[min(self.index, len(self._road_of) - 1)]
        return self._limits.get(road, DEFAULT_SPEED_LIMIT)


def route_from_context(context: Any) -> CarlaRoute:
    """The route of an episode on a CARLA map: the ego starts on the catalog's lane key at its s; the
    context's ``extras`` may hold ``signal_state`` (a server's light states) and ``route_planner`` (a
    :class:`RoutePlanner` to reuse: building one reads the whole topology)."""
    carla_map = context.road_map
    road, lane = lane_from_key(context.ego_lane)
    start = carla_map.get_waypoint_xodr(road, lane, float(context.ego_s))
    if start is None:
        raise UserInputError(f"the ego's lane (road {road}, lane {lane}, s = {context.ego_s:.1f}) is not on the "
                             f"CARLA map {context.map_name}")
    rng = np.random.default_rng(np.random.SeedSequence([context.seed, 7]))
    return CarlaRoute(carla_map, start, rng, context.extras.get("signal_state"), context.extras.get("route_planner"),
                      context.extras.get("speed_limits"))
