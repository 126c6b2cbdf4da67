"""The ``genesis-rl`` command line. Bad input exits with status 2 and a one-line message, no traceback."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from genesis_rl import __version__
from genesis_rl.errors import UserInputError


def _cmd_scenes(args: argparse.Namespace) -> int:
    from genesis_rl.io_utils import ensure_writable
    from genesis_rl.lite.maps import MAP_NAMES
    from genesis_rl.scenes.lite_generator import DEFAULT_COUNTS, generate_catalog

    if args.backend != "lite":
        raise UserInputError(f"--backend '{args.backend}' is not available yet; allowed: lite")
    if args.map not in MAP_NAMES:
        raise UserInputError(f"--map '{args.map}' is unknown; allowed: {', '.join(MAP_NAMES)}")
    count = args.count if args.count is not None else DEFAULT_COUNTS[args.map]
    if count < 1:
        raise UserInputError(f"--count must be >= 1, got {count}")
    out = Path(args.out)
    ensure_writable(out, args.force)
    t0 = time.perf_counter()
    catalog = generate_catalog(args.map, count, args.seed, progress=not args.quiet)
    catalog.save(out)
    print(json.dumps({"out": str(out), "map": args.map, "scenes": count, "seed": args.seed,
                      "seconds": round(time.perf_counter() - t0, 2)}))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from genesis_rl.bench import bench_sim

    print(json.dumps(bench_sim(physics_steps=args.steps, frames=args.frames, render=not args.no_render), indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="genesis-rl",
        description="GENESIS-RL: find natural edge cases for autonomous driving by turning the weather.",
    )
    p.add_argument("--version", action="version", version=f"genesis-rl {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    sc = sub.add_parser("scenes", help="generate a scene catalog (JSON) for a map")
    sc.add_argument("--map", default="urban", help="map name: urban (train) or highway (test)")
    sc.add_argument("--count", type=int, default=None, help="number of scenes (default: 1202 urban, 1199 highway)")
    sc.add_argument("--seed", type=int, default=0, help="catalog seed: the same seed gives the same catalog")
    sc.add_argument("--backend", default="lite", help="simulator backend (lite)")
    sc.add_argument("--out", required=True, help="output catalog file (.json)")
    sc.add_argument("--force", action="store_true", help="overwrite an existing output")
    sc.add_argument("--quiet", action="store_true", help="no progress bar")
    sc.set_defaults(func=_cmd_scenes)

    bench = sub.add_parser("bench", help="benchmarks; prints JSON")
    bench.add_argument("what", choices=["sim"], help="sim: physics steps/s and rendered frames/s")
    bench.add_argument("--steps", type=int, default=2000, help="physics steps to time")
    bench.add_argument("--frames", type=int, default=100, help="frames to time per resolution")
    bench.add_argument("--no-render", action="store_true", help="physics only")
    bench.set_defaults(func=_cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except UserInputError as err:
        print(f"genesis-rl {args.command}: error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
