"""``genesis-rl train``: train the weather agent (SB3 PPO or SAC, or a recurrent PPO) against the system under test."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from genesis_rl.commands.cli_args import SEED, add_odd_arguments, add_scale_arguments, odd_overrides_from_args
from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.backends import (
    add_backend_arguments,
    env_overrides_from_args,
)

#: training.config.ALGORITHMS, written out: importing the config here would load the env for ``--help``
ALGORITHMS = ("ppo", "sac", "recurrent_ppo")


def _csv_list(text: str | None) -> list[str] | None:
    return None if text is None else [t.strip() for t in text.split(",") if t.strip()]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``train`` command's flags."""
    p = sub.add_parser("train", help="train the weather agent (SB3 PPO or SAC, or a recurrent PPO) against the system "
                                     "under test")
    p.add_argument("--config", default=None, help="TOML config (default: the paper's values, configs/paper.toml)")
    p.add_argument("--out", required=True, help="run folder (runs/NAME)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--force", action="store_true", help="replace an existing run folder")
    p.add_argument("--envs", type=int, default=None,
                   help="parallel environments (subprocesses, or Ray actors with --executor ray)")
    p.add_argument("--steps", type=int, default=None, help="total env steps (train.total_timesteps)")
    p.add_argument("--algorithm", choices=ALGORITHMS, default=None,
                   help="the learner (train.algorithm): ppo (the paper's, [ppo]), sac ([sac]) or recurrent_ppo "
                        "(an LSTM policy with memory of the episode: [ppo] and [recurrent])")
    p.add_argument("--n-steps", type=int, default=None, help="steps per PPO update (ppo.n_steps)")
    p.add_argument("--episode-steps", type=int, default=None, help="steps per episode (env.episode_steps)")
    p.add_argument("--seed", type=int, action=SEED, default=None, help="training seed (train.seed)")
    p.add_argument("--knobs", default=None, help="comma list of knobs the agent turns (env.knobs)")
    p.add_argument("--disable-knobs", default=None, help="comma list of knobs held at their start (ablation)")
    p.add_argument("--system", default=None, help="system under test (env.system)")
    p.add_argument("--map", default=None, help="map of generated scenes (env.map)")
    p.add_argument("--scenes", type=int, default=None, help="number of generated scenes (env.scenes)")
    p.add_argument("--catalog", default=None, help="scene catalog file (env.catalog)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_odd_arguments(p)
    add_backend_arguments(p, default=None)
    add_scale_arguments(p, "--envs")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.training.config import load_run_config
    from genesis_rl.training.train import train
    from genesis_rl.world.knobs import KNOBS

    env: dict = {}
    for flag, key in (("knobs", "knobs"), ("disable_knobs", "disabled_knobs")):
        names = _csv_list(getattr(args, flag))
        if names is not None:
            bad = [n for n in names if n not in KNOBS]
            if bad:
                raise UserInputError(f"--{flag.replace('_', '-')}: unknown knob(s) {bad}; allowed: {', '.join(KNOBS)}")
            env[key] = names
    for flag in ("system", "scenes", "catalog", "map"):
        if getattr(args, flag) is not None:
            env[flag] = getattr(args, flag)
    if args.map is not None and args.catalog is not None:  # the run would record a map its scenes are not on
        from genesis_rl.campaigns.campaign_spec import campaign_map

        campaign_map(args.map, args.catalog)
    env.update(env_overrides_from_args(args))  # --backend carla --carla-host H ... override the config's [env]
    env.update(odd_overrides_from_args(args))
    tr: dict = {}
    for flag, key in (("envs", "envs"), ("steps", "total_timesteps"), ("seed", "seed"), ("algorithm", "algorithm")):
        if getattr(args, flag) is not None:
            tr[key] = getattr(args, flag)
    ppo = {"n_steps": args.n_steps} if args.n_steps is not None else {}
    if args.episode_steps is not None:
        env["episode_steps"] = args.episode_steps
    extra = {k: v for k, v in tr.items() if k != "total_timesteps"}
    if args.resume and (env or extra or ppo or args.config):
        raise UserInputError("--resume continues a run with its own config.toml; only --steps may change")
    cfg = load_run_config(args.config, {"env": env, "train": tr, "ppo": ppo})
    from genesis_rl.distributed.servers import parse_servers
    from genesis_rl.distributed.settings import ExecutorSettings
    from genesis_rl.sim.backends import servers_text

    scale = ExecutorSettings(kind=args.executor, ray_address=args.ray_address,
                             servers=parse_servers(servers_text(args)))
    result = train(cfg, Path(args.out), force=args.force, resume=args.resume, progress=not args.quiet,
                   argv=sys.argv, total_timesteps=args.steps if args.resume else None, inputs=[args.config],
                   scale=scale)
    print(json.dumps(result, indent=2))
    return 0
