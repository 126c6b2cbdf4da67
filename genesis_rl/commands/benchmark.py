"""``genesis-rl benchmark``: the matrix of zoo members x adversaries x trials, and its leaderboard.

A top-level command (as ``export_cmd``): ``benchmark`` runs campaigns through ``evaluation``; the zoo and the
metrics live in ``zoo`` and ``benchmark``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from genesis_rl.benchmark.reproduce import DEFAULT_RERUNS
from genesis_rl.benchmark.transfer import DEFAULT_TUNING_SCENES
from genesis_rl.core.errors import UserInputError


def _names(text: str, flag: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(","))
    if not all(names):
        raise UserInputError(f"{flag} '{text}' has an empty name; give a comma list such as sunny,random")
    return names


def _agents(given: list[str] | None) -> dict[str, tuple[str, ...]]:
    """``--agent MEMBER=RUN`` (repeated, or comma lists): each member's trained agents, in the order given."""
    out: dict[str, list[str]] = {}
    for text in given or ():
        for item in text.split(","):
            member, sep, run = item.partition("=")
            if not sep or not member.strip() or not run.strip():
                raise UserInputError(f"--agent '{item}': give MEMBER=RUN, e.g. latency_braking=runs/zoo_latency_sac_s0")
            if not Path(run.strip()).exists():
                raise UserInputError(f"--agent '{item}': run folder '{run.strip()}' does not exist")
            out.setdefault(member.strip(), []).append(run.strip())
    return {m: tuple(r) for m, r in out.items()}


def _estimates(given: list[str] | None) -> dict[str, Path]:
    """``--estimate MEMBER=FOLDER`` (repeated): each member's failure-rate estimate for the page."""
    out: dict[str, Path] = {}
    for item in given or ():
        member, sep, folder = item.partition("=")
        if not sep or not member.strip() or not folder.strip():
            raise UserInputError(f"--estimate '{item}': give MEMBER=FOLDER, e.g. glare_blind=runs/est_glare_is_s0")
        out[member.strip()] = Path(folder.strip())
    return out


#: the flags that set the matrix, at their defaults (``--smoke`` refuses any other value: it has its own matrix)
MATRIX_DEFAULTS: dict[str, object] = {
    "members": None, "policies": "sunny,random,constant,random_search,cmaes,cem,mcts", "agent": None, "trials": 10,
    "scenes": 5, "seed": 0, "steps": None, "start": "natural", "search_budget": None, "reruns": DEFAULT_RERUNS,
    "protocol": "per_scene", "tuning_scenes": DEFAULT_TUNING_SCENES}


def run(args: argparse.Namespace) -> int:
    from genesis_rl.benchmark.matrix import ADVERSARIES, SMOKE, BenchmarkSpec
    from genesis_rl.sut.zoo.members import ZOO

    if args.list:
        from genesis_rl.commands.zoo import print_members

        print_members()
        print(f"policies: {', '.join(ADVERSARIES)} (and agent:RUN with --agent MEMBER=RUN)")
        return 0
    if args.out is None:
        raise UserInputError("--out is required (the benchmark folder), unless --list")
    from genesis_rl.core import limits

    for value, flag, limit in ((args.workers, "--workers", limits.WORKERS),
                               (args.search_budget, "--search-budget", limits.SEARCH_BUDGET)):
        if value is not None:
            if value < 1:
                raise UserInputError(f"{flag} = {value}; allowed: an integer >= 1")
            limit.check(value, flag)
    options: dict = {}
    if args.search_budget is not None:
        options["search_budget"] = args.search_budget
    if args.smoke:
        # the smoke matrix is fixed: a matrix flag beside it would be dropped without a word
        given = [f"--{k.replace('_', '-')}" for k, v in MATRIX_DEFAULTS.items() if getattr(args, k) != v]
        if given:
            raise UserInputError(f"--smoke runs its own fixed matrix ({len(SMOKE.members)} members, {SMOKE.trials} "
                                 f"trials); {', '.join(given)} would be ignored: drop them or drop --smoke")
        spec = SMOKE
    else:
        spec = BenchmarkSpec(
            members=_names(args.members, "--members") if args.members else tuple(ZOO),
            policies=_names(args.policies, "--policies"), trials=args.trials, scenes=args.scenes, seed=args.seed,
            steps=args.steps, options=options, start=args.start, agents=_agents(args.agent), reruns=args.reruns,
            protocol=args.protocol, tuning_scenes=args.tuning_scenes)
    executor = None
    if args.executor == "ray" or args.ray_address:
        from genesis_rl.distributed.settings import ExecutorSettings

        executor = ExecutorSettings(kind="ray", workers=args.workers, ray_address=args.ray_address)
    from genesis_rl.benchmark.matrix import run_benchmark

    board = run_benchmark(spec, Path(args.out), force=args.force, resume=args.resume, workers=args.workers,
                          executor=executor, progress=not args.quiet, estimates=_estimates(args.estimate),
                          parallel=args.parallel)
    short = {m: {p: {k: c[k] for k in ("confirmed_rate", "reproduction_rate", "falsification_rate", "triggered",
                                        "median_steps_to_failure", "distinct_in_odd_failures",
                                        "false_alarm_candidates", "false_alarms_beyond_sunny")}
                 for p, c in cells.items()} for m, cells in board["cells"].items()}
    print(json.dumps({"out": args.out, "cells": short, "average_rank": board["ranks"]["average_rank"],
                      "friedman_p": board["ranks"]["friedman_p"]}, indent=2))
    print(f"leaderboard: {Path(args.out) / 'leaderboard.html'}")
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from genesis_rl.commands.cli_args import SEED

    bm = subparsers.add_parser(
        "benchmark", help="every adversary on systems whose weaknesses are known (the zoo); a leaderboard",
        description="Run the matrix zoo members x policies x trials (each trial a campaign with its own seed) "
                    "on local processes or Ray, resumable, and write leaderboard.json and leaderboard.html: "
                    "confirmed failures (triggered, avoidable, reproduced on fresh world seeds: the rank's score), "
                    "falsification rate, reached/triggered, steps to the first in-ODD failure (Kaplan-Meier), "
                    "distinct failures, false alarms on the controls, ranks with Friedman's and Iman-Davenport's "
                    "tests (docs/zoo.md).")
    bm.add_argument("--out", default=None, help="benchmark folder")
    bm.add_argument("--members", default=MATRIX_DEFAULTS["members"],
                    help="comma list of zoo members (default: all; see --list)")
    bm.add_argument("--policies", default=MATRIX_DEFAULTS["policies"],
                    help=f"comma list of adversaries (default: {MATRIX_DEFAULTS['policies']}; random_search is "
                         "random at the searches' budget)")
    bm.add_argument("--agent", action="append", default=MATRIX_DEFAULTS["agent"], metavar="MEMBER=RUN",
                    help="a trained agent (a run folder of genesis-rl train on the member's env) to play on MEMBER "
                         "as the policy agent:RUN, one campaign a trial on the trial's scenes; repeat it (or give a "
                         "comma list) for more training seeds. --resume may add agents to a finished benchmark")
    bm.add_argument("--estimate", action="append", metavar="MEMBER=FOLDER",
                    help="show a genesis-rl estimate folder's failure rate under natural conditions on the member's "
                         "section (repeat per member)")
    bm.add_argument("--trials", type=int, default=MATRIX_DEFAULTS["trials"],
                    help="trials (campaign seeds) per member (default 10)")
    bm.add_argument("--scenes", type=int, default=MATRIX_DEFAULTS["scenes"],
                    help="scenes a trial plays per policy (default 5)")
    bm.add_argument("--seed", type=int, action=SEED, default=MATRIX_DEFAULTS["seed"],
                    help="the first trial's seed; trial k uses seed + k")
    bm.add_argument("--steps", type=int, default=MATRIX_DEFAULTS["steps"],
                    help="steps per episode, the simulator-step budget of a trial (default: each member's own)")
    bm.add_argument("--start", choices=("natural", "fixed"), default=MATRIX_DEFAULTS["start"],
                    help="natural (default): each adversary chooses where the knobs that cannot move within an "
                         "episode start (the sun); fixed: every episode from the start weather")
    bm.add_argument("--search-budget", type=int, default=MATRIX_DEFAULTS["search_budget"],
                    help="episodes a search adversary (random_search, corner_search, cmaes, cem, mcts, goexplore) may "
                         "spend per scene")
    bm.add_argument("--reruns", type=int, default=MATRIX_DEFAULTS["reruns"],
                    help="re-runs of every reported in-ODD failure on fresh world seeds (traffic, sensor noise) that "
                         "no adversary saw; a failure is confirmed when at least half reproduce it; 0: none "
                         f"(default {DEFAULT_RERUNS})")
    bm.add_argument("--protocol", choices=("per_scene", "transfer"), default=MATRIX_DEFAULTS["protocol"],
                    help="per_scene (default): each adversary searches the scene it is scored on; transfer: the "
                         "searches tune on --tuning-scenes other scenes a trial and replay their best schedule, "
                         "start included, once on each held-out scene, where every adversary plays one episode "
                         "(the costs, tuning and training included, and the agents' break-even go on the page)")
    bm.add_argument("--tuning-scenes", type=int, default=MATRIX_DEFAULTS["tuning_scenes"],
                    help=f"under --protocol transfer: tuning scenes a trial (default {DEFAULT_TUNING_SCENES})")
    bm.add_argument("--smoke", action="store_true",
                    help="a tiny matrix that runs in about a minute and finds one failure (latency_braking and "
                         "builtin_braking, sunny and constant, 2 trials of one 160-step scene, 2 re-runs)")
    bm.add_argument("--list", action="store_true", help="list the zoo's members and the adversaries, and exit")
    bm.add_argument("--workers", type=int, default=1, help="parallel processes (or Ray actors)")
    bm.add_argument("--parallel", choices=("auto", "campaigns", "episodes"), default="auto",
                    help="how the workers share the matrix: campaigns (whole campaigns side by side, one process "
                         "or Ray actor each), episodes (one campaign at a time, its episodes spread), or auto "
                         "(default: campaigns with at least two campaigns a worker to run); the same figures")
    bm.add_argument("--executor", choices=("local", "ray"), default="local", help="where the episodes run")
    bm.add_argument("--ray-address", default=None, help="a running Ray cluster (implies --executor ray)")
    bm.add_argument("--resume", action="store_true", help="continue the benchmark in --out where it stopped")
    bm.add_argument("--force", action="store_true", help="replace an existing benchmark folder")
    bm.add_argument("--quiet", action="store_true", help="no progress bar")
    bm.set_defaults(func=run)
    return bm
