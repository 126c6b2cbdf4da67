"""``highway``: the test town, like CARLA's Town05. A three-lane-each-way highway loop with curves and
hills, joined at two signalised junctions to a small town grid; pine-covered hills around it."""

from __future__ import annotations

import numpy as np

from genesis_rl.sim.lite.maps.lane_graph import Building, NetworkSpec, RoadMap, Tree, build_network
from genesis_rl.sim.lite.maps.scenery import RoadMask, grid_network, lane_and_junction_points, overlaps_any

TOWN_SPACING = 90.0
TOWN_N = 3
TOWN_CENTER = np.array([90.0, 90.0])
HOUSE_COLORS = [
    (0.85, 0.80, 0.70), (0.70, 0.45, 0.35), (0.90, 0.88, 0.82), (0.55, 0.58, 0.50), (0.75, 0.65, 0.45),
]


def elevation(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rolling hills away from the town (flat within ~200 m of its centre), up to about +/-12 m."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    r = np.hypot(x - TOWN_CENTER[0], y - TOWN_CENTER[1])
    t = np.clip((r - 200.0) / 200.0, 0.0, 1.0)
    ramp = t * t * (3 - 2 * t)
    hills = 8.0 * np.sin(x / 170.0) * np.cos(y / 210.0) + 4.0 * np.sin((x + 0.6 * y) / 120.0 + 1.0)
    return ramp * hills


def build_highway() -> RoadMap:
    nodes, roads = grid_network(TOWN_N, TOWN_SPACING, lanes_each_way=2)
    east, north = 2 * TOWN_N + 1, 1 * TOWN_N + 2  # (180, 90) and (90, 180)
    # highway loop: leaves the town eastward, sweeps around through the hills and re-enters from the north
    loop = [(300, 95), (470, 60), (640, 150), (760, 330), (730, 560), (560, 720), (330, 760),
            (150, 640), (95, 420), (90, 300)]
    roads.append((east, north, loop, 3))
    # a second, shorter highway spur: west side of town out to the hills and back to the south edge
    spur = [(-120, 160), (-300, 120), (-380, -60), (-260, -230), (-60, -220), (60, -140)]
    roads.append((TOWN_N - 1, TOWN_N, spur, 3))  # node (0, 180) -> node (90, 0)
    corners = {0, TOWN_N - 1, (TOWN_N - 1) * TOWN_N, TOWN_N * TOWN_N - 1}
    radius = {n: (20.0 if n in corners else 13.0) for n in nodes}
    radius[east] = radius[north] = 15.0
    radius[TOWN_N - 1] = radius[3] = 16.0
    lanes, road_list, junctions = build_network(NetworkSpec(nodes, roads, radius))

    rng = np.random.default_rng(505)
    bounds = (-520.0, -380.0, 900.0, 900.0)
    pts = lane_and_junction_points(lanes, junctions)
    road_clear = RoadMask(pts, bounds, clearance=14.0)
    buildings: list[Building] = []
    occupied = np.zeros((0, 4))
    town_lo, town_hi = -40.0, (TOWN_N - 1) * TOWN_SPACING + 40.0
    for _ in range(900):
        x, y = rng.uniform(town_lo, town_hi), rng.uniform(town_lo, town_hi)
        w, d = rng.uniform(8, 16), rng.uniform(8, 14)
        cx = np.array([x - w / 2, x + w / 2, x - w / 2, x + w / 2, x])
        cy = np.array([y - d / 2, y + d / 2, y + d / 2, y - d / 2, y])
        if not road_clear.free(cx, cy).all():
            continue
        if overlaps_any(occupied, x, y, w, d, margin=3.0):
            continue
        buildings.append(Building(x, y, 0.0, w, d, float(rng.uniform(5, 11)),
                                  HOUSE_COLORS[int(rng.integers(len(HOUSE_COLORS)))]))
        occupied = np.vstack([occupied, [x, y, w, d]])
    trees: list[Tree] = []
    tree_clear = RoadMask(pts, bounds, clearance=12.0)
    cand = rng.uniform([bounds[0], bounds[1]], [bounds[2], bounds[3]], size=(9000, 2))
    r_town = np.hypot(cand[:, 0] - TOWN_CENTER[0], cand[:, 1] - TOWN_CENTER[1])
    # pines thicken with distance from the town, in clumps
    clumps = 0.55 + 0.45 * np.sin(cand[:, 0] / 37) * np.cos(cand[:, 1] / 29)
    density = np.clip((r_town - 150) / 200, 0.05, 1.0) * clumps
    keep = tree_clear.free(cand[:, 0], cand[:, 1]) & (rng.uniform(size=len(cand)) < density)
    for x, y in cand[keep][:4000]:
        if overlaps_any(occupied, x, y, 0.0, 0.0, margin=3.0):
            continue
        trees.append(Tree(float(x), float(y), float(rng.uniform(9, 17)), "pine"))
    return RoadMap(
        name="highway",
        lanes=lanes,
        roads=road_list,
        junctions=junctions,
        elevation=elevation,
        buildings=buildings,
        trees=trees,
        bounds=bounds,
        ground_color=(0.30, 0.40, 0.22),
    ).finalize()
