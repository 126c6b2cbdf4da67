"""Scene catalogs on the lite maps: the generator (ego, lead ahead in its lane, neighbour front-right, 27
others nearby) and the checks a catalog must pass to be driven on lite (each vehicle on its lane, none
overlapping another at the start).

The module-level functions :func:`check_map`, :func:`default_count`, :func:`generate` and
:func:`check_catalog` are the lite backend's scene source (:class:`genesis_rl.sim.backends.SceneSource`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterator

import numpy as np
from tqdm import tqdm

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.interface import ConnectionSettings
from genesis_rl.sim.lite.collisions import colliding_pairs
from genesis_rl.sim.lite.maps import MAP_NAMES, load_map
from genesis_rl.sim.lite.maps.lane_graph import DS, RoadMap
from genesis_rl.world.scenes.catalog import Catalog, Scene, VehicleSpec
from genesis_rl.world.scenes.placement import TRAFFIC, draw_autopilot, draw_make, fits
from genesis_rl.world.scenes.vehicles import MAKES, PALETTE

#: the paper's catalog sizes: Town10 (train) and Town05 (test)
DEFAULT_COUNTS = {"urban": 1202, "highway": 1199}
N_VEHICLES = 30
RADIUS = 90.0  # others are placed within this distance of the ego [m]
POSE_TOLERANCE_M = 1.0  # a vehicle's x, y may differ this much from its lane's point at s


#: free-flow scenes start the ego on a lane of at least this speed limit [m/s] (a motorway's main line) ...
FREE_FLOW_MIN_LIMIT = 20.0
#: ... with at least this much lane ahead of it [m]: a 512-step episode at 25 m/s drives 640 m
FREE_FLOW_RUN_M = 700.0
#: free flow's others start at least this time gap [s] behind whoever is ahead of them in their lane ...
FREE_FLOW_TIME_GAP = 1.5
#: ... so its 27 others, spaced so, are placed within this distance of the ego [m] (RADIUS holds too few gaps)
FREE_FLOW_RADIUS = 200.0


_COLOURS = list(PALETTE)


def _vehicle(rng, road_map, role, lane, s, make, speed_frac, traffic: str = "mixed") -> VehicleSpec:
    x, y, _, yaw = road_map.pose(lane, s)
    succ = road_map.lanes[lane].successors
    color_name = _COLOURS[int(rng.integers(len(_COLOURS)))]  # rng.choice(_COLOURS)'s draw, without its overhead
    limit = road_map.speed_limit(lane)
    ap = None if role == "ego" else draw_autopilot(rng, limit, role, traffic)
    return VehicleSpec(role, make, color_name, PALETTE[color_name], int(lane), float(s), x, y, yaw,
                       float(limit * speed_frac), int(succ[int(rng.integers(len(succ)))]), ap)


def _safe_headway(spec: VehicleSpec, placed: list[VehicleSpec], time_gap: float = 0.0) -> bool:
    """No vehicle starts so close behind another in its lane that it cannot brake in time: the bumper gap
    must exceed 2 m + 2.5 s x the closing speed (a follower at 21 m/s 4 m behind an ego at 15 m/s would
    rear-end it whatever the ego does), plus ``time_gap`` s x the follower's speed (free flow's 1.5 s: no one
    starts tailgating, and no other car slips in between the ego and its lead)."""
    half = MAKES[spec.make].length / 2.0
    for other in placed:
        if other.lane != spec.lane:
            continue
        gap = abs(other.s - spec.s) - half - MAKES[other.make].length / 2.0
        behind, ahead = (spec, other) if spec.s < other.s else (other, spec)
        if gap < 2.0 + 2.5 * max(0.0, behind.speed - ahead.speed) + time_gap * behind.speed:
            return False
    return True


def generate_scene(road_map: RoadMap, index: int, seed: int, traffic: str = "mixed") -> Scene:
    """Scene ``index`` of a catalog, from its own ``seed``; ``traffic`` as :data:`TRAFFIC` says."""
    if traffic == "free_flow":
        return _free_flow_scene(road_map, index, seed)
    rng = np.random.default_rng(seed)
    # ego: a road lane with a lane to its right (for the neighbour) and room for the lead ahead
    egos = [ln.id for ln in road_map.lanes if ln.road >= 0 and ln.right >= 0 and ln.length > 60]
    while True:
        lane = int(egos[int(rng.integers(len(egos)))])
        length = road_map.length[lane]
        s_ego = float(rng.uniform(5.0, length - 45.0))
        gap_lead = float(rng.uniform(15.0, min(40.0, length - s_ego - 5.0)))
        speed = float(rng.uniform(0.5, 0.9))
        ego = _vehicle(rng, road_map, "ego", lane, s_ego, str(rng.choice(["sedan", "hatchback", "suv"])), speed)
        lead = _vehicle(rng, road_map, "lead", lane, s_ego + gap_lead, draw_make(rng), speed)
        right = road_map.lanes[lane].right
        s_nb = min(s_ego + float(rng.uniform(6.0, 20.0)), road_map.length[right] - 1.0)
        neighbour = _vehicle(rng, road_map, "neighbour", right, s_nb, draw_make(rng), speed)
        placed = [ego]
        if fits(lead, placed) and fits(neighbour, placed + [lead]):
            placed += [lead, neighbour]
            break
    return _with_others(rng, road_map, index, placed, ego, "mixed")


def _free_flow_scene(road_map: RoadMap, index: int, seed: int) -> Scene:
    """A scene in free-flowing traffic: the ego at 90-100 % of a main line's limit with room ahead for a whole
    episode, its lead 1.5-2.0 s ahead at the same speed (a following headway a careful driver keeps: UN R157's
    reference avoids a lead braking at 6 m/s^2 from it) and cruising a little slower, nobody stopping on its own.
    What the lead then does is the actor knobs' doing alone, from the first step on."""
    rng = np.random.default_rng(seed)
    egos = [ln.id for ln in road_map.lanes if ln.road >= 0 and ln.right >= 0
            and road_map.length[ln.id] > FREE_FLOW_RUN_M + 10.0 and road_map.speed_limit(ln.id) >= FREE_FLOW_MIN_LIMIT]
    if not egos:
        raise UserInputError(f"map '{road_map.name}' has no lane for free-flowing traffic (at least "
                             f"{FREE_FLOW_RUN_M:g} m at {FREE_FLOW_MIN_LIMIT:g} m/s or more, with a lane to its "
                             "right); allowed there: traffic 'mixed'")
    while True:
        lane = int(egos[int(rng.integers(len(egos)))])
        s_ego = float(rng.uniform(5.0, road_map.length[lane] - FREE_FLOW_RUN_M))
        speed = float(rng.uniform(0.9, 1.0))
        headway = float(rng.uniform(1.5, 2.0)) * speed * road_map.speed_limit(lane)
        ego = _vehicle(rng, road_map, "ego", lane, s_ego, str(rng.choice(["sedan", "hatchback", "suv"])), speed,
                       "free_flow")
        lead = _vehicle(rng, road_map, "lead", lane, s_ego + headway, draw_make(rng), speed, "free_flow")
        right = road_map.lanes[lane].right
        s_nb = min(s_ego + float(rng.uniform(10.0, 30.0)), road_map.length[right] - 1.0)
        neighbour = _vehicle(rng, road_map, "neighbour", right, s_nb, draw_make(rng), speed, "free_flow")
        placed = [ego]
        if fits(lead, placed) and fits(neighbour, placed + [lead]):
            placed += [lead, neighbour]
            break
    return _with_others(rng, road_map, index, placed, ego, "free_flow")


def _with_others(rng: np.random.Generator, road_map: RoadMap, index: int, placed: list[VehicleSpec],
                 ego: VehicleSpec, traffic: str) -> Scene:
    """The scene: ``placed`` (ego, lead, neighbour) and others on lane samples within RADIUS of the ego (under
    free flow within FREE_FLOW_RADIUS at 85-100 % of their lane's limit, else 0-90 %), none overlapping or too
    close behind another, then the scene's episode seed and signal offset."""
    pts = road_map.points
    on_road = np.array([road_map.lanes[k].road >= 0 for k in range(len(road_map.lanes))])[road_map.point_lane]
    radius = FREE_FLOW_RADIUS if traffic == "free_flow" else RADIUS
    near = np.flatnonzero(on_road & ((pts[:, 0] - ego.x) ** 2 + (pts[:, 1] - ego.y) ** 2 < radius**2))
    tries = 0
    while len(placed) < N_VEHICLES and tries < 5000:
        tries += 1
        k = int(near[int(rng.integers(len(near)))])
        lane = int(road_map.point_lane[k])
        s = (k - int(road_map.offset[lane])) * DS
        if s < 3.0 or s > road_map.length[lane] - 3.0:
            continue
        make = draw_make(rng)
        frac = float(rng.uniform(0.85, 1.0) if traffic == "free_flow" else rng.uniform(0.0, 0.9))
        spec = _vehicle(rng, road_map, "other", lane, s, make, frac, traffic)
        time_gap = FREE_FLOW_TIME_GAP if traffic == "free_flow" else 0.0
        if fits(spec, placed) and _safe_headway(spec, placed, time_gap):
            placed.append(spec)
    if len(placed) < N_VEHICLES:
        raise RuntimeError(f"scene {index}: could only place {len(placed)} vehicles")
    return Scene(index, road_map.name, int(rng.integers(2**31)), float(rng.uniform(0, road_map.timing.cycle)),
                 tuple(placed))


def iter_scenes(map_name: str, count: int, seed: int, traffic: str = "mixed") -> Iterator[Scene]:
    road_map = load_map(map_name)
    seeds = np.random.SeedSequence(seed).spawn(count)
    for i, ss in enumerate(seeds):
        yield generate_scene(road_map, i, int(ss.generate_state(1)[0]), traffic)


#: catalogs this process generated, newest last: a campaign generates its map's whole catalog (1,199 scenes,
#: half a minute) to draw a few scenes from it, and a benchmark or a test session runs many campaigns on the
#: same map and seed. A Catalog is frozen, and its scenes depend on nothing but this key.
_GENERATED: OrderedDict[tuple[str, int, int, str], Catalog] = OrderedDict()
_GENERATED_KEPT = 4


def generate_catalog(map_name: str, count: int, seed: int, progress: bool = False, traffic: str = "mixed") -> Catalog:
    if traffic not in TRAFFIC:
        raise UserInputError(f"traffic = '{traffic}' is unknown; allowed: {', '.join(TRAFFIC)}")
    key = (map_name, int(count), int(seed), traffic)
    if key in _GENERATED:
        _GENERATED.move_to_end(key)
        return _GENERATED[key]
    scenes = iter_scenes(map_name, count, seed, traffic)
    if progress:
        scenes = tqdm(scenes, total=count, desc=f"scenes {map_name}", unit="scene")
    catalog = Catalog(map_name, seed, "lite", tuple(scenes))
    _GENERATED[key] = catalog
    while len(_GENERATED) > _GENERATED_KEPT:
        _GENERATED.popitem(last=False)
    return catalog


# -- the scene source of the lite backend (genesis_rl.sim.backends.SceneSource) ---------------------------------
def check_map(map_name: str, field: str) -> None:
    """``field`` (the setting that named the map, e.g. ``--map``) must name a lite map."""
    if map_name not in MAP_NAMES:
        raise UserInputError(f"{field} '{map_name}' is unknown; allowed: {', '.join(MAP_NAMES)}")


def default_count(map_name: str) -> int:
    """The paper's catalog size for the map (see :data:`DEFAULT_COUNTS`)."""
    return DEFAULT_COUNTS[map_name]


def generate(map_name: str, count: int, seed: int, settings: ConnectionSettings, progress: bool = False) -> Catalog:
    """``count`` scenes on ``map_name``; lite needs no connection (``settings`` is ignored)."""
    return generate_catalog(map_name, count, seed, progress=progress)


def check_catalog(catalog: Catalog) -> None:
    """What the schema cannot check: the map is a lite map, every vehicle's pose agrees with its lane and
    s, and no two vehicles of a scene start inside each other."""
    if catalog.map not in MAP_NAMES:
        raise UserInputError(f"catalog field 'map' = '{catalog.map}'; allowed: {', '.join(MAP_NAMES)}")
    road_map = load_map(catalog.map)
    for i, scene in enumerate(catalog.scenes):
        where = f"scenes[{i}]"
        for j, v in enumerate(scene.vehicles):
            _check_on_lane(road_map, f"{where}.vehicles[{j}]", v.lane, v.next_lane, v.s, v.x, v.y)
        _check_apart(scene.vehicles, where)


def _check_on_lane(road_map: RoadMap, where: str, lane: int, next_lane: int, s: float, x: float, y: float) -> None:
    """A lite vehicle is placed from its lane and s; its x, y must agree with them, so that what the catalog
    says and what the simulator does are the same scene."""
    n = len(road_map.lanes)
    if not (0 <= lane < n and 0 <= next_lane < n):
        raise UserInputError(f"catalog: '{where}.lane'/'next_lane' out of the map's lanes 0..{n - 1}")
    length = float(road_map.length[lane])
    if not 0.0 <= s <= length:
        raise UserInputError(f"catalog: '{where}.s' = {s}; lane {lane} is {length:.1f} m long "
                             f"(allowed 0..{length:.1f})")
    successors = road_map.lanes[lane].successors
    if next_lane not in successors:
        raise UserInputError(f"catalog: '{where}.next_lane' = {next_lane} does not follow lane {lane}; "
                             f"allowed: {', '.join(map(str, successors))}")
    px, py, _, _ = road_map.pose(lane, s)
    off = math.hypot(px - x, py - y)
    if off > POSE_TOLERANCE_M:
        raise UserInputError(f"catalog: '{where}.x'/'y' = ({x:.2f}, {y:.2f}) lie {off:.1f} m from lane {lane} at "
                             f"s = {s:.1f} ({px:.2f}, {py:.2f}); allowed: within {POSE_TOLERANCE_M} m")


def _check_apart(vehicles: tuple[VehicleSpec, ...], where: str) -> None:
    """No two lite vehicles may start inside each other (the simulator would report a collision at step 0)."""
    pairs = colliding_pairs(*(np.array(col, float) for col in zip(
        *((v.x, v.y, v.yaw, MAKES[v.make].length, MAKES[v.make].width) for v in vehicles), strict=True)))
    if pairs:
        i, j = pairs[0]
        raise UserInputError(f"catalog: '{where}.vehicles[{i}]' and '{where}.vehicles[{j}]' overlap at the start; "
                             "allowed: vehicles whose boxes do not intersect")
