"""Costs of the CARLA map path, offline (no server): OpenDRIVE export, carla.Map build, the route planner, and
one controller step on a CARLA route against one on the lite route of the same lane.

    python scripts/bench_carla_route.py --map urban      # prints JSON
"""

from __future__ import annotations

import argparse
import json
import math
import time

import carla
import numpy as np

from genesis_rl.sim.carla.lanes import lane_key
from genesis_rl.sim.carla.route import RoutePlanner, route_from_context
from genesis_rl.sim.interface import ActorState, CameraConfig, SensorFrame
from genesis_rl.sim.lite.maps import load_map
from genesis_rl.sim.lite.maps.opendrive import odr_lane_ids, signal_plan, to_opendrive
from genesis_rl.sut.system.builtin import BlindSystem
from genesis_rl.sut.system.protocol import EpisodeContext
from genesis_rl.world.scenes.vehicles import MAKES


def _seconds(fn, repeat: int = 5) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _step_cost(context: EpisodeContext, x: float, y: float, yaw: float, steps: int = 2000) -> float:
    """Mean seconds per system step of a kinematic ego driving the route (BlindSystem: controller only)."""
    make = MAKES["sedan"]
    system = BlindSystem()
    system.reset(context)
    frame = SensorFrame(0, np.zeros((8, 8, 3), np.uint8), np.full((8, 8), np.inf, np.float32), [])
    v, spent = 8.0, 0.0
    for k in range(steps):
        ego = ActorState(0, "ego", "sedan", x, y, 0.0, yaw, 0.0, v, make.length, make.width, make.height)
        t0 = time.perf_counter()
        c = system.step(frame, ego, k * context.dt).control
        spent += time.perf_counter() - t0
        v = max(v + (3.0 * c.throttle - 8.0 * c.brake) * context.dt, 0.0)
        yaw += v / make.wheelbase * math.tan(-c.steer * math.radians(35.0)) * context.dt
        x += v * math.cos(yaw) * context.dt
        y += v * math.sin(yaw) * context.dt
    return spent / steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", default="urban")
    args = ap.parse_args()
    lite = load_map(args.map)
    text = to_opendrive(lite)
    cmap = carla.Map(args.map, text)
    planner = RoutePlanner(cmap)
    lite_lane = lite.roads[1].forward_lanes[0]
    road, lane = odr_lane_ids(lite)[lite_lane]
    s0 = 10.0
    common = dict(camera=CameraConfig(), dt=0.05, seed=0, ego_s=s0)
    carla_ctx = EpisodeContext("carla", args.map, cmap, ego_lane=lane_key(road, lane),
                               extras={"plan_route": route_from_context, "route_planner": planner,
                                       "signal_state": signal_plan(lite)}, **common)
    lite_ctx = EpisodeContext("lite", args.map, lite, ego_lane=lite_lane,
                              ego_next_lane=lite.lanes[lite_lane].successors[0], **common)
    x, y, _, yaw = lite.pose(lite_lane, s0)
    out = {
        "map": args.map,
        "export_s": round(_seconds(lambda: to_opendrive(lite)), 4),
        "xodr_kib": len(text.encode()) // 1024,
        "carla_map_build_s": round(_seconds(lambda: carla.Map(args.map, text)), 4),
        "route_planner_build_s": round(_seconds(lambda: RoutePlanner(cmap)), 4),
        "route_first_plan_s": round(_seconds(lambda: route_from_context(carla_ctx)), 4),
        "controller_step_ms_carla_route": round(1e3 * _step_cost(carla_ctx, x, y, yaw), 4),
        "controller_step_ms_lite_route": round(1e3 * _step_cost(lite_ctx, x, y, yaw), 4),
    }
    out["carla_over_lite"] = round(out["controller_step_ms_carla_route"] / out["controller_step_ms_lite_route"], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
