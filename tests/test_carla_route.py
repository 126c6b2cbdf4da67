"""The built-in controller on CARLA maps, offline: lite maps exported as OpenDRIVE, loaded by the real
``carla`` client as ``carla.Map`` (no server), planned on with the CARLA route planner and driven by the
built-in controller with a kinematic ego. Skipped as a module without the ``carla`` extra."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

carla = pytest.importorskip("carla")

from genesis_rl.sim.carla.lanes import lane_key  # noqa: E402
from genesis_rl.sim.carla.route import CarlaRoute, RoutePlanner, route_from_context, speed_limits  # noqa: E402
from genesis_rl.sim.interface import ActorState, CameraConfig, SensorFrame  # noqa: E402
from genesis_rl.sim.lite.maps import load_map  # noqa: E402
from genesis_rl.sim.lite.maps.lane_graph import DS, LANE_WIDTH  # noqa: E402
from genesis_rl.sim.lite.maps.opendrive import odr_lane_ids, signal_plan, to_opendrive  # noqa: E402
from genesis_rl.sut.system.builtin import BlindSystem, plan_route  # noqa: E402
from genesis_rl.sut.system.protocol import EpisodeContext  # noqa: E402
from genesis_rl.world.scenes.vehicles import MAKES  # noqa: E402

MAPS = ("urban", "highway")
EXTRAS = {"plan_route": route_from_context}  # what the CARLA backend hands the system


@pytest.fixture(scope="module")
def exported():
    """name -> (lite map, OpenDRIVE text, carla.Map)."""
    out = {}
    for name in MAPS:
        lite = load_map(name)
        text = to_opendrive(lite)
        out[name] = (lite, text, carla.Map(name, text))
    return out


def _lateral(wp, x: float, y: float) -> float:
    """Signed distance of (x, y) (our frame) from the waypoint's lane centre, across the lane."""
    yaw = -math.radians(wp.transform.rotation.yaw)
    dx, dy = x - wp.transform.location.x, y + wp.transform.location.y
    return -math.sin(yaw) * dx + math.cos(yaw) * dy


# -- the export -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", MAPS)
def test_export_loads_in_carla_with_the_lite_lanes(exported, name) -> None:
    lite, text, cmap = exported[name]
    assert to_opendrive(lite) == text  # deterministic
    root = ET.fromstring(text)
    roads = {int(r.get("id")): r for r in root.iter("road")}
    ids = odr_lane_ids(lite)
    for road in lite.roads:  # lane count, widths and lengths of every lite road
        el = roads[road.id]
        lanes = [int(ln.get("id")) for ln in el.iter("lane") if ln.get("id") != "0"]
        assert sorted(lanes) == sorted([k for n in range(1, road.lanes_each_way + 1) for k in (n, -n)])
        assert {float(w.get("a")) for w in el.iter("width")} == {LANE_WIDTH}
        centre = np.hypot(*np.diff(road.centerline, axis=0).T).sum()
        assert float(el.get("length")) == pytest.approx(centre, rel=2e-4)
        wp = cmap.get_waypoint_xodr(road.id, -1, 1.0)
        assert wp.lane_width == pytest.approx(LANE_WIDTH)
    lateral = []
    for ln in lite.lanes:  # every lite lane's centre is the CARLA lane's centre
        for i in range(2, len(ln.xy) - 2, 15):
            x, y = ln.xy[i]
            wp = cmap.get_waypoint(carla.Location(float(x), -float(y), float(lite.points[lite.offset[ln.id] + i, 2])))
            if (wp.road_id, wp.lane_id) == ids[ln.id]:
                lateral.append(abs(_lateral(wp, x, y)))
    assert len(lateral) > 0.99 * sum(len(range(2, len(ln.xy) - 2, 15)) for ln in lite.lanes)
    assert max(lateral) < 0.05
    lights = cmap.get_all_landmarks_of_type("1000001")
    approaches = {(ln.road, ln.signal) for ln in lite.lanes if ln.signal is not None}
    assert len(lights) == len(approaches) > 0


def test_speed_limits_and_elevation_come_through(exported) -> None:
    lite, text, cmap = exported["highway"]
    limits = speed_limits(cmap.to_opendrive())
    assert limits[len(lite.roads) - 1] == pytest.approx(25.0) and limits[0] == pytest.approx(12.0)
    loop = lite.lanes[lite.roads[12].forward_lanes[0]]
    i = len(loop.xy) // 3
    wp = cmap.get_waypoint_xodr(12, -1, i * DS)
    z_lite = lite.elevation(np.array([wp.transform.location.x]), np.array([-wp.transform.location.y]))[0]
    assert abs(z_lite) > 1.0 and wp.transform.location.z == pytest.approx(z_lite, abs=0.3)


# -- the planner --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", MAPS)
def test_planner_graph_is_the_lite_lane_graph(exported, name) -> None:
    lite, _, cmap = exported[name]
    planner = RoutePlanner(cmap)
    ids = odr_lane_ids(lite)
    lite_edges = {(ids[ln.id], ids[s]) for ln in lite.lanes for s in ln.successors}
    follow = {(planner.segments[a].key[::2], planner.segments[b].key[::2])
              for a, b, kind in planner.graph.edges(data="kind") if kind == "follow"}
    assert follow == lite_edges
    changes = [(a, b) for a, b, kind in planner.graph.edges(data="kind") if kind != "follow"]
    same_road = {(ids[ln.id], ids[ln.left]) for ln in lite.lanes if ln.left >= 0}
    assert {(planner.segments[a].key[::2], planner.segments[b].key[::2]) for a, b in changes} == (
        same_road | {(b, a) for a, b in same_road})


def _start(lite, cmap, road: int, s: float):
    ids = odr_lane_ids(lite)
    r, lane = ids[lite.roads[road].forward_lanes[0]]
    return r, lane, cmap.get_waypoint_xodr(r, lane, s)


@pytest.mark.parametrize("name", MAPS)
def test_route_follows_lanes_turns_changes_lanes_and_finds_the_lights(exported, name) -> None:
    lite, _, cmap = exported[name]
    planner = RoutePlanner(cmap)
    _, _, start = _start(lite, cmap, 1, 20.0)
    routes = [CarlaRoute(cmap, start, np.random.default_rng(seed), signal_plan(lite), planner=planner)
              for seed in range(6)]
    again = CarlaRoute(cmap, start, np.random.default_rng(0), signal_plan(lite), planner=planner)
    assert np.array_equal(again.xy, routes[0].xy)  # the same seed, the same route
    assert len({r.xy[:400].tobytes() for r in routes}) > 1  # other seeds, other turns
    turns, changes = 0, 0
    for route in routes:
        for _ in range(4):  # the ego moves on: the route extends, drawing new destinations
            route.update(*route.xy[min(route.index + 600, len(route.xy) - 1)])
        xy = route.xy
        step = np.hypot(*np.diff(xy, axis=0).T)
        assert step.min() > 0.4 * DS and step.max() < 1.1 * DS
        on_lane = np.array([o != "left" and o != "right" for o in route.options])
        for k in np.flatnonzero(on_lane)[::20]:  # on a lane centre of the lite map, except inside a lane change
            pts = lite.points[:, :2]
            assert np.min(np.hypot(*(pts - xy[k]).T)) < 0.3
        h = np.unwrap(np.arctan2(*np.diff(xy, axis=0).T[::-1]))
        junction = np.array([o == "junction" for o in route.options[:-1]])
        turns += int(np.sum(np.abs(np.diff(h)[junction[1:]])) > math.radians(60))
        lane_change = [o in ("left", "right") for o in route.options]
        changes += sum(1 for a, b in zip(lane_change, lane_change[1:], strict=False) if b and not a)
        for stop in route.stops:  # each stop line is where a signalised lite lane ends
            p = xy[int(round(stop.s / DS))]
            ends = np.array([ln.xy[-1] for ln in lite.lanes if ln.signal is not None])
            assert np.min(np.hypot(*(ends - p).T)) < 1.0
    assert turns > 0 and changes > 0 and sum(len(r.stops) for r in routes) > 0


# -- the built-in controller on a carla.Map ------------------------------------------------------------------
def _drive(system, context, steps: int, x: float, y: float, yaw: float, v: float):
    """A kinematic bicycle under the system's controls; returns the trace (x, y, speed, status, distance
    from the front bumper to the next stop line on the route, inf without one)."""
    make = MAKES["sedan"]
    system.reset(context)
    frame = SensorFrame(0, np.zeros((8, 8, 3), np.uint8), np.full((8, 8), np.inf, np.float32), [])
    trace = []
    for k in range(steps):
        ego = ActorState(0, "ego", "sedan", x, y, 0.0, yaw, 0.0, v, make.length, make.width, make.height)
        out = system.step(frame, ego, k * context.dt)
        c = out.control
        a = 3.0 * c.throttle - 8.0 * c.brake
        delta = -c.steer * math.radians(35.0)
        v = max(v + a * context.dt, 0.0)
        yaw += v / make.wheelbase * math.tan(delta) * context.dt
        x += v * math.cos(yaw) * context.dt
        y += v * math.sin(yaw) * context.dt
        sig = system.controller.route.next_signal(80.0)
        trace.append((x, y, v, out.status, math.inf if sig is None else sig[0] - 0.5 * make.length))
    return trace


@pytest.mark.parametrize("name", MAPS)
def test_builtin_system_drives_a_carla_map_stops_at_red_and_keeps_its_lane(exported, name) -> None:
    lite, _, cmap = exported[name]
    road, lane, start = _start(lite, cmap, 1, 10.0)
    context = EpisodeContext("carla", name, cmap, CameraConfig(), 0.05, seed=3, ego_lane=lane_key(road, lane),
                             ego_s=10.0, extras=EXTRAS | {"signal_state": signal_plan(lite)})
    route = plan_route(context)
    assert isinstance(route, CarlaRoute)
    x, y = start.transform.location.x, -start.transform.location.y
    yaw = -math.radians(start.transform.rotation.yaw)
    system = BlindSystem()
    # 150 s: long enough to arrive at some light early in its red phase. In 60 s the ego met one red late in
    # its phase and crept to the line as it turned green (genesis-rl 0.18 drives the highway's bends faster)
    trace = _drive(system, context, 3000, x, y, yaw, 5.0)
    statuses = [t[3] for t in trace]
    speeds = np.array([t[2] for t in trace])
    xy = np.array([t[:2] for t in trace])
    travelled = np.hypot(*np.diff(xy, axis=0).T).sum()
    assert travelled > 150.0  # with a red light or two to wait at (up to 18 s each)
    route = system.controller.route
    assert any(o == "junction" for o in route.options[: route.index])
    for p in xy[::10]:  # never off its route by half a lane
        assert np.min(np.hypot(*(route.xy - p).T)) < 0.5 * LANE_WIDTH
    # it met a red light, stopped for it, and stood before the stop line
    stopped = (np.array(statuses) == "red_light") & (speeds < 0.05)
    assert stopped.sum() > 20
    assert min(t[4] for t, s in zip(trace, stopped, strict=True) if s) > -0.5


def test_map_export_command(tmp_path) -> None:
    import subprocess
    import sys

    out = tmp_path / "urban.xodr"
    cmd = [sys.executable, "-m", "genesis_rl", "map", "export", "--map", "urban", "--out", str(out)]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    assert out.read_text() == to_opendrive(load_map("urban"))
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "--force" in again.stderr  # never overwritten without --force
    bad = subprocess.run([*cmd[:5], "--map", "town", "--out", str(tmp_path / "t.xodr")], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "allowed: urban, highway" in bad.stderr


@pytest.mark.parametrize("spec", ["builtin", "oracle"])
def test_builtin_systems_reset_and_step_on_a_carla_context(exported, spec) -> None:
    from genesis_rl.sut.system.protocol import load_system

    lite, _, cmap = exported["highway"]
    road, lane, start = _start(lite, cmap, 12, 50.0)
    context = EpisodeContext("carla", "highway", cmap, CameraConfig(), 0.05, seed=0, ego_lane=lane_key(road, lane),
                             ego_s=50.0, extras=EXTRAS | {"signal_state": signal_plan(lite)})
    system = load_system(spec)
    system.reset(context)
    make = MAKES["sedan"]
    loc, yaw = start.transform.location, -math.radians(start.transform.rotation.yaw)
    ego = ActorState(0, "ego", "sedan", loc.x, -loc.y, 0.0, yaw, 0.0, 10.0, make.length, make.width, make.height)
    frame = SensorFrame(0, np.full((240, 320, 3), 120, np.uint8), np.full((240, 320), 80.0, np.float32), [])
    out = system.step(frame, ego, 0.0)
    assert out.detections == [] and out.lead_distance is None and out.status == "cruise"
    # on the highway loop at 10 m/s, under its 13.9 m/s cruise cap: it speeds up and steers gently
    assert out.control.throttle > 0.0 and abs(out.control.steer) < 0.1


def test_a_map_without_a_planner_is_refused_by_name(exported) -> None:
    from genesis_rl.core.errors import UserInputError

    _, _, cmap = exported["urban"]
    context = EpisodeContext("mysim", "urban", cmap, CameraConfig(), 0.05, seed=0)
    with pytest.raises(UserInputError, match=r"backend 'mysim' gave neither \(its map is a Map\)"):
        BlindSystem().reset(context)


def test_routes_keep_every_stop_line_and_never_step_sideways(exported) -> None:
    """Regression (review of 0.9.0): a lane change that ended at a section's end dropped that section's stop
    line, and a leg that ended on a lane change stepped 3.5 m across at a right angle."""
    lite, _, cmap = exported["urban"]
    planner = RoutePlanner(cmap)
    ids = odr_lane_ids(lite)
    ends = np.array([ln.xy[-1] for ln in lite.lanes if ln.signal is not None])
    changes = 0
    for seed in range(3):
        for road in range(0, len(lite.roads), 3):
            for lid in lite.roads[road].forward_lanes:
                r, lane = ids[lid]
                route = CarlaRoute(cmap, cmap.get_waypoint_xodr(r, lane, 10.0), np.random.default_rng(seed),
                                   signal_plan(lite), planner=planner)
                for _ in range(6):
                    route.update(*route.xy[min(route.index + 600, len(route.xy) - 1)])
                xy = route.xy
                h = np.unwrap(np.arctan2(*np.diff(xy, axis=0).T[::-1]))
                assert np.abs(np.diff(h)).max() < math.radians(45), (seed, road, lane)
                changes += sum(1 for a, b in zip(route.options, route.options[1:], strict=False)
                               if b in ("left", "right") and a not in ("left", "right"))
                stops = np.array([s.s / DS for s in route.stops])
                passed = np.flatnonzero(np.min(np.hypot(*(xy[:, None, :] - ends[None]).transpose(2, 0, 1)), axis=1)
                                        < 0.3)
                for k in passed[passed < len(xy) - 50]:  # each stop line the route crosses has its stop
                    assert len(stops) and np.min(np.abs(stops - k)) <= 4, (seed, road, lane, int(k))
    assert changes > 10


# -- lane-change markings, read per waypoint as CARLA's planner reads them ------------------------------------
def _marked(text: str, marks) -> str:
    """The export with each broken lane mark replaced by ``marks(road length)``: (sOffset, allowed) pairs,
    a forbidding stretch drawn solid with laneChange="none"."""
    root = ET.fromstring(text)
    for road in root.iter("road"):
        length = float(road.get("length"))
        for lane in road.iter("lane"):
            for rm in [m for m in lane.findall("roadMark") if m.get("type") == "broken"]:
                at = list(lane).index(rm)
                lane.remove(rm)
                for k, (s0, allowed) in enumerate(marks(length)):
                    attrs = {**rm.attrib, "sOffset": f"{s0:g}", "laneChange": "both" if allowed else "none",
                             "type": "broken" if allowed else "solid"}
                    lane.insert(at + k, ET.Element("roadMark", attrs))
    return ET.tostring(root, encoding="unicode")


def _change_edges(planner) -> int:
    return sum(1 for *_, kind in planner.graph.edges(data="kind") if kind != "follow")


@pytest.mark.parametrize("name", MAPS)
def test_export_writes_each_marks_lane_change(exported, name) -> None:
    """Without a laneChange attribute CARLA allows changes both ways across every mark, solid or not: the
    export says 'none' at the road's edge and the centre line, 'both' between lanes of one direction."""
    lite, _, cmap = exported[name]
    n_each = {int(r.get("id")): max(abs(int(ln.get("id"))) for ln in r.iter("lane"))
              for r in ET.fromstring(to_opendrive(lite)).iter("road") if r.get("junction") == "-1"}
    wrong, seen = 0, 0
    for w in cmap.generate_waypoints(10.0):
        if w.is_junction:
            continue
        n, k = n_each[w.road_id], abs(w.lane_id)
        expected = (carla.LaneChange.Left if k > 1 else 0) | (carla.LaneChange.Right if k < n else 0)
        seen += 1
        wrong += int(w.lane_change) != int(expected)
    assert seen > 500 and wrong == 0


def test_a_lane_change_edge_is_kept_where_its_section_starts_forbidden(exported) -> None:
    """Regression (issue 36): the marking was read at a section's first waypoint only; with the first 8 m
    of every road marked 'none', half the lane-change edges (48 of 96 on urban) disappeared."""
    lite, text, cmap = exported["urban"]
    full = _change_edges(RoutePlanner(cmap))
    late = _change_edges(RoutePlanner(carla.Map("urban", _marked(text, lambda length: [(0, False), (8, True)]))))
    none = _change_edges(RoutePlanner(carla.Map("urban", _marked(text, lambda length: [(0, False)]))))
    assert full == late == 96 and none == 0


def test_lane_changes_happen_only_where_the_marking_allows_them(exported) -> None:
    """Regression (issue 36): a change was always blended over a section's last 20 m; with the last 30 m
    (in s) of every road marked 'none', 279 of 280 lane-change points lay where changing is forbidden."""
    lite, text, _ = exported["urban"]
    cmap = carla.Map("urban", _marked(text, lambda length: [(0, True), (max(length - 30.0, 0.0), False)]))
    lengths = {int(r.get("id")): float(r.get("length")) for r in ET.fromstring(text).iter("road")}
    planner, ids = RoutePlanner(cmap), odr_lane_ids(lite)
    points, forbidden = 0, 0
    for seed in range(3):
        for road in range(0, len(lite.roads), 2):
            r, lane = ids[lite.roads[road].forward_lanes[0]]
            route = CarlaRoute(cmap, cmap.get_waypoint_xodr(r, lane, 5.0), np.random.default_rng(seed),
                               signal_plan(lite), planner=planner)
            for _ in range(4):
                route.update(*route.xy[min(route.index + 600, len(route.xy) - 1)])
            for k in np.flatnonzero([o in ("left", "right") for o in route.options]):
                x, y = route.xy[k]
                wp = cmap.get_waypoint(carla.Location(float(x), float(-y), 0.0))
                points += 1
                forbidden += int(wp.s > lengths[wp.road_id] - 30.0 + 1.0)
    assert points > 200 and forbidden == 0
