"""``genesis-rl map``: a lite map as OpenDRIVE text (for CARLA and Scenic)."""

from __future__ import annotations

import argparse
import json
import time


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``map`` command's flags."""
    p = sub.add_parser("map", help="export a lite map as OpenDRIVE (for CARLA and Scenic)",
                       description="Write a lite map as OpenDRIVE 1.4: roads, lanes, junctions and traffic lights. "
                       "CARLA builds a carla.Map from it without a server, a CARLA server drives it with "
                       "client.generate_opendrive_world, and Scenic loads it as a road network (docs/carla.md).")
    p.add_argument("action", choices=["export"], help="what to do: export")
    p.add_argument("--map", default="urban", help="lite map: urban or highway (default: urban)")
    p.add_argument("--format", default="xodr", choices=["xodr"], help="output format (default: xodr, OpenDRIVE 1.4)")
    p.add_argument("--out", default=None, help="output file (default: MAP.xodr in the current folder)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.core.files.output_paths import output_file
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive
    from genesis_rl.sim.lite.scenes import check_map

    check_map(args.map, "--map")
    out = output_file(args.out if args.out else f"{args.map}.xodr", args.force)
    t0 = time.perf_counter()
    road_map = load_map(args.map)
    text = to_opendrive(road_map)
    out.write_text(text)
    print(json.dumps({"out": str(out), "map": args.map, "format": args.format, "roads": len(road_map.roads),
                      "junctions": len(road_map.junctions), "lanes": len(road_map.lanes), "bytes": len(text.encode()),
                      "seconds": round(time.perf_counter() - t0, 2)}), file=out.status)
    return 0
