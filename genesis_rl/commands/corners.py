"""``genesis-rl corners``: the best constant schedule, every corner of the action box on training scenes."""

from __future__ import annotations

import argparse
import json
import time

from genesis_rl.commands.cli_args import SEED, count
from genesis_rl.core import limits


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``corners`` command's flags."""
    p = sub.add_parser("corners", help="find the best constant schedule: every corner of the action box on "
                       "training scenes", description="Play every corner of the action box (+-1 on each knob that "
                       "can move) on the same training scenes and seeds; rank by mean return, then collisions. The "
                       "winner is the open-loop baseline for evaluate --policies constant --constant-action.")
    p.add_argument("--config", default=None, help="TOML config whose [env] is used (e.g. configs/reactive.toml)")
    p.add_argument("--map", default=None, help="map of the scenes (default: the config's env.map, the training map)")
    p.add_argument("--scenes", type=int, action=count(1, limits.SCENES), default=10,
                   help="training scenes drawn by --seed (default: 10)")
    p.add_argument("--seed", type=int, action=SEED, default=0, help="draws the scenes and their episode seeds")
    p.add_argument("--steps", type=int, action=count(1, limits.SIM_STEPS), default=None,
                   help="steps per episode (default: the config's)")
    p.add_argument("--out", required=True, help="output JSON")
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.analysis.corners import search_corners
    from genesis_rl.campaigns.campaign_files import env_named_files
    from genesis_rl.campaigns.campaign_spec import pick_scenes
    from genesis_rl.core.files.output_paths import check_inputs, output_file
    from genesis_rl.env import GenesisEnv
    from genesis_rl.training.config import load_run_config

    out = output_file(args.out, args.force, inputs=[args.config])
    env_over: dict = {"episode_steps": args.steps} if args.steps is not None else {}
    if args.map is not None:
        env_over["map"] = args.map
    cfg = load_run_config(args.config, {"env": env_over})
    # the files the config names, the system's weights among them
    check_inputs(args.out, [cfg.env.catalog, cfg.env.odd, cfg.env.rulebook,
                            *env_named_files({"system_kwargs": cfg.env.system_kwargs})])
    env = GenesisEnv(cfg.env)
    try:
        pairs = pick_scenes(len(env.catalog.scenes), args.scenes, args.seed)
        t0 = time.perf_counter()
        rows = search_corners(env, [s for s, _ in pairs], [e for _, e in pairs], progress=not args.quiet)
    finally:
        env.close()
    best = ",".join(f"{v:g}" for v in rows[0]["action"])
    out.write_json({"config": args.config, "map": cfg.env.map, "scenes": pairs, "knobs": list(cfg.env.knobs),
                            "steps": cfg.env.episode_steps, "best_constant_action": best, "corners": rows,
                            "seconds": round(time.perf_counter() - t0, 1)}, indent=2)
    print(json.dumps({"out": str(out), "best_constant_action": best, "mean_return": round(rows[0]["mean_return"], 3),
                      "collisions": rows[0]["collisions"], "corners": len(rows),
                      "then": f"genesis-rl evaluate --policies constant --constant-action {best} ..."}, indent=2),
          file=out.status)
    return 0
