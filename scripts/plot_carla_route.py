"""Plot a lite map's OpenDRIVE export as CARLA reads it, with a route of the CARLA route planner.

    python scripts/plot_carla_route.py --map urban --seed 0 --out docs/images/carla_route_urban.png

Grey: the lite lanes. Blue dots: CARLA waypoints every 2 m on the carla.Map built from the export (no server).
Red: a route planned by genesis_rl.sim.carla.route (junction turns, lane changes in orange), with its stop
lines (black bars) from the exported traffic lights.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import carla  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from genesis_rl.sim.carla.route import CarlaRoute, RoutePlanner  # noqa: E402
from genesis_rl.sim.lite.maps import load_map  # noqa: E402
from genesis_rl.sim.lite.maps.opendrive import odr_lane_ids, signal_plan, to_opendrive  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", default="urban")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--road", type=int, default=1, help="lite road the route starts on (forward lane 0)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    lite = load_map(args.map)
    cmap = carla.Map(args.map, to_opendrive(lite))
    fig, ax = plt.subplots(figsize=(11, 8))
    for ln in lite.lanes:
        ax.plot(ln.xy[:, 0], ln.xy[:, 1], color="0.75", lw=3.0, solid_capstyle="butt", zorder=1)
    wps = cmap.generate_waypoints(2.0)
    ax.scatter([w.transform.location.x for w in wps], [-w.transform.location.y for w in wps], s=1.0, c="tab:blue",
               zorder=2, label=f"CARLA waypoints on the export ({len(wps)})")
    ids = odr_lane_ids(lite)
    road, lane = ids[lite.roads[args.road].forward_lanes[0]]
    route = CarlaRoute(cmap, cmap.get_waypoint_xodr(road, lane, 10.0), np.random.default_rng(args.seed),
                       signal_plan(lite), planner=RoutePlanner(cmap))
    for _ in range(40):  # the ego moves on (projection looks 40 m ahead): the route extends leg by leg
        route.update(*route.xy[min(route.index + 70, len(route.xy) - 1)])
    xy, opts = route.xy, np.array(route.options)
    ax.plot(xy[:, 0], xy[:, 1], color="tab:red", lw=1.4, zorder=3, label=f"planned route ({len(xy) * 0.5:.0f} m)")
    change = np.isin(opts, ["left", "right"])
    ax.scatter(xy[change, 0], xy[change, 1], s=8, c="tab:orange", zorder=4, label="lane changes")
    ax.plot(*xy[0], "o", color="tab:red", ms=8, zorder=5, label="start")
    for stop in route.stops:
        i = min(int(round(stop.s / 0.5)), len(xy) - 2)
        d = xy[i + 1] - xy[i]
        n = np.array([-d[1], d[0]]) / max(np.hypot(*d), 1e-9) * 2.0
        ax.plot([xy[i, 0] - n[0], xy[i, 0] + n[0]], [xy[i, 1] - n[1], xy[i, 1] + n[1]], color="k", lw=2.5, zorder=6)
    ax.plot([], [], color="k", lw=2.5, label=f"stop lines on the route ({len(route.stops)})")
    ax.set_aspect("equal")
    ax.set_title(f"lite '{args.map}' exported as OpenDRIVE, read by carla.Map (no server); route seed {args.seed}")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)


if __name__ == "__main__":
    main()
