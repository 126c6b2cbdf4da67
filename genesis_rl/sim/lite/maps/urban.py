"""``urban``: the training town, like CARLA's Town10. A 4x4 grid of streets 110 m apart with two lanes
each way, signalised 4-way intersections inside, T-junctions on the edges, and blocks of buildings."""

from __future__ import annotations

import numpy as np

from genesis_rl.sim.lite.maps.lane_graph import Building, NetworkSpec, RoadMap, Tree, build_network, flat
from genesis_rl.sim.lite.maps.scenery import RoadMask, grid_network, lane_and_junction_points, overlaps_any

SPACING = 110.0
N = 4
FACADES = [
    (0.72, 0.68, 0.62), (0.60, 0.55, 0.50), (0.80, 0.78, 0.74), (0.55, 0.40, 0.33), (0.45, 0.47, 0.52),
    (0.70, 0.62, 0.50), (0.35, 0.36, 0.40), (0.85, 0.82, 0.70), (0.50, 0.30, 0.25), (0.62, 0.66, 0.70),
]


def build_urban() -> RoadMap:
    nodes, roads = grid_network(N, SPACING, lanes_each_way=2)
    corners = {0, N - 1, (N - 1) * N, N * N - 1}
    radius = {n: (22.0 if n in corners else 12.0) for n in nodes}
    lanes, road_list, junctions = build_network(NetworkSpec(nodes, roads, radius))

    rng = np.random.default_rng(1010)  # the map is fixed: its own constant seed
    margin = 70.0
    bounds = (-margin, -margin, (N - 1) * SPACING + margin, (N - 1) * SPACING + margin)
    mask = RoadMask(lane_and_junction_points(lanes, junctions), bounds, clearance=12.0)
    buildings: list[Building] = []
    # rows of buildings along every street side, set back behind the sidewalk
    occupied = np.zeros((0, 4))
    for _ in range(2600):
        x = rng.uniform(bounds[0] + 5, bounds[2] - 5)
        y = rng.uniform(bounds[1] + 5, bounds[3] - 5)
        w, d = rng.uniform(12, 30), rng.uniform(12, 26)
        # orient to the nearer street axis
        yaw = 0.0
        corners_xy = np.array([[x - w / 2, y - d / 2], [x + w / 2, y + d / 2], [x - w / 2, y + d / 2],
                               [x + w / 2, y - d / 2], [x, y]])
        if not mask.free(corners_xy[:, 0], corners_xy[:, 1]).all():
            continue
        if overlaps_any(occupied, x, y, w, d, margin=1.0):
            continue
        h = float(rng.choice([rng.uniform(8, 18), rng.uniform(18, 45)], p=[0.6, 0.4]))
        color = FACADES[int(rng.integers(len(FACADES)))]
        buildings.append(Building(x, y, yaw, w, d, h, color))
        occupied = np.vstack([occupied, [x, y, w, d]])
    # street trees on the sidewalks
    trees: list[Tree] = []
    near = RoadMask(lane_and_junction_points(lanes, junctions), bounds, clearance=9.0)
    for _ in range(1500):
        x, y = rng.uniform(bounds[0], bounds[2]), rng.uniform(bounds[1], bounds[3])
        if near.free(np.array([x]), np.array([y]))[0] and not mask.free(np.array([x]), np.array([y]))[0]:
            if not overlaps_any(occupied, x, y, 0.0, 0.0, margin=2.0):
                trees.append(Tree(x, y, float(rng.uniform(5, 9)), "broadleaf"))
    return RoadMap(
        name="urban",
        lanes=lanes,
        roads=road_list,
        junctions=junctions,
        elevation=flat,
        buildings=buildings,
        trees=trees,
        bounds=bounds,
        ground_color=(0.46, 0.45, 0.43),
    ).finalize()
