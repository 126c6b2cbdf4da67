"""``genesis-rl evaluate``: a campaign of weather policies on held-out scenes; summary and report."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from genesis_rl.campaigns.summary import summary_rule_metrics
from genesis_rl.commands.cli_args import add_odd_arguments, add_scale_arguments, count, odd_overrides_from_args
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.backends import add_backend_arguments, check_backend_setting, env_overrides_from_args
from genesis_rl.world.scenes.placement import TRAFFIC

if TYPE_CHECKING:
    from genesis_rl.distributed.settings import ExecutorSettings



def _constant_action(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UserInputError(f"--constant-action = '{text}': expected numbers in [-1, 1], e.g. 1,1,1,1,0") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise UserInputError(f"--constant-action = '{text}': expected numbers in [-1, 1], e.g. 1,1,1,1,0")
    return values


def executor_from_args(args: argparse.Namespace, backend: str) -> ExecutorSettings:
    """Where the campaign's episodes run, checked before anything is written."""
    from genesis_rl.distributed.servers import parse_servers, servers_for_workers
    from genesis_rl.distributed.settings import ExecutorSettings
    from genesis_rl.sim.backends import servers_text

    servers = servers_for_workers(backend, parse_servers(servers_text(args)), args.workers)
    return ExecutorSettings(kind=args.executor, workers=args.workers, ray_address=args.ray_address,
                            servers=tuple(servers))


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``evaluate`` command's flags."""
    p = sub.add_parser("evaluate", help="evaluation campaign: weather policies on held-out scenes; summary, report")
    p.add_argument("--agent", default=None, help="trained run folder (runs/NAME) or agent .zip")
    p.add_argument("--policies", default="sunny,random,agent",
                   help="comma list: sunny, random, constant, agent, cmaes, cem (search baselines) or "
                        "package.module:Class")
    p.add_argument("--map", default=None, help="test map (default: the --catalog's map, else highway; the agent "
                                               "trains on urban)")
    p.add_argument("--catalog", default=None, help="test catalog file (default: the map's generated catalog)")
    p.add_argument("--catalog-seed", type=int, action=count(0), default=0, help="seed of the generated test catalog")
    p.add_argument("--traffic", default="mixed", choices=TRAFFIC,
                   help="traffic of the generated test catalog: mixed (default, the paper's: the lead stops now "
                        "and then) or free_flow (lite; everyone cruises near the limit, nobody stops on its own)")
    p.add_argument("--scenes", type=int, action=count(1, limits.SCENES), default=50,
                   help="scenes picked from the catalog by --seed")
    p.add_argument("--seed", type=int, action=count(0), default=0, help="campaign seed: scene choice and episode seeds")
    p.add_argument("--steps", type=int, action=count(1, limits.SIM_STEPS), default=512,
                   help="steps per episode (0.05 s each)")
    p.add_argument("--system", default=None, help="system under test (default: the agent's)")
    p.add_argument("--weights", default=None,
                   help="detector weights of the system under test (builtin or yolo; default: the shipped ones; "
                        "coco: a model folder): "
                        "an agent against a detector it never trained with")
    p.add_argument("--config", default=None, help="TOML with an [env] table, when no --agent is given")
    p.add_argument("--search-budget", type=int, action=count(2, limits.SEARCH_BUDGET), default=8,
                   help="episodes per scene a search baseline may spend")
    p.add_argument("--search-segments", type=int, action=count(1), default=4,
                   help="piecewise-constant segments of a searched schedule")
    p.add_argument("--constant-action", default=None, metavar="A,B,...",
                   help="policy 'constant': its action, one value in [-1, 1] per knob (default: 1 on every knob)")
    p.add_argument("--start", default="fixed", choices=["fixed", "natural"],
                   help="where episodes start: fixed (the start weather, default) or natural (each policy chooses "
                        "the knobs that cannot move within an episode, the sun under natural dynamics: random "
                        "draws them inside the ODD, constant takes its corner, the searches search them)")
    p.add_argument("--records", default="failures", choices=["failures", "all"],
                   help="write replayable edge-case records for failing episodes only, or for all")
    p.add_argument("--retries", type=int, action=count(0, limits.RETRIES), default=2,
                   help="times an episode is retried after reconnecting when the simulator dies mid-episode")
    p.add_argument("--workers", type=int, action=count(1, limits.WORKERS), default=1,
                   help="parallel workers (processes, or Ray actors with --executor ray), one episode each at a time")
    add_scale_arguments(p, "--workers")
    p.add_argument("--out", default=None, help="campaign folder (default: AGENT/eval)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted campaign in --out")
    p.add_argument("--force", action="store_true", help="replace an existing campaign folder")
    p.add_argument("--no-report", action="store_true", help="skip report.html")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_odd_arguments(p)
    p.add_argument("--no-counterfactual", action="store_true",
                   help="skip the oracle replay of each collision (by default on with an ODD): blame then rests "
                        "on the visibility evidence alone")
    add_backend_arguments(p, default=None)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    # counts first, before any policy is imported: a refused budget answers at once
    if args.search_segments > args.steps:
        raise UserInputError(f"--search-segments = {args.search_segments} must be at most --steps = {args.steps} "
                             "(a segment is at least one step)")
    from genesis_rl.adversaries import resolve_policy
    from genesis_rl.campaigns.campaign import CampaignSpec, env_settings_for, run_campaign
    from genesis_rl.campaigns.campaign_spec import campaign_map

    policies = tuple(p.strip() for p in args.policies.split(",") if p.strip())
    if not policies:
        raise UserInputError("--policies is empty; allowed: sunny, random, constant, agent, cmaes, cem or "
                             "package.module:Class")
    if len(set(policies)) != len(policies):
        raise UserInputError(f"--policies names a policy twice: {','.join(policies)}")
    for p in policies:
        resolve_policy(p)
    if any(resolve_policy(p).needs_agent for p in policies) and not args.agent:
        raise UserInputError("policy 'agent' needs --agent runs/NAME (a run folder of genesis-rl train)")
    agent = str(Path(args.agent)) if args.agent else None
    env = env_settings_for(agent, args.config, args.system, args.weights)
    env.update(env_overrides_from_args(args))
    env.update(odd_overrides_from_args(args))
    executor = executor_from_args(args, env.get("backend", "lite"))
    check_backend_setting(env.get("backend", "lite"), args.catalog, "--backend", "--catalog")
    map_name = campaign_map(args.map, args.catalog)  # a catalog of one map is not run under another's name
    spec = CampaignSpec(policies=policies, map=map_name, catalog=args.catalog, catalog_seed=args.catalog_seed,
                        scenes=args.scenes, seed=args.seed, steps=args.steps, agent=agent, env=env,
                        records=args.records, traffic=args.traffic,
                        options={"search_budget": args.search_budget, "search_segments": args.search_segments,
                                 "retries": args.retries,
                                 **({"constant_action": _constant_action(args.constant_action)}
                                    if args.constant_action is not None else {}),
                                 **({"start": args.start} if args.start != "fixed" else {}),
                                 **({"counterfactual": False} if args.no_counterfactual else {})})
    if "agent" in policies and env.get("start_head") and args.start != "natural":
        print("warning: the agent was trained with env.start_head (its first action chooses where the held knobs, "
              "such as the sun, start), but --start is fixed, so it plays from the start weather; pass --start "
              "natural to let it choose", file=sys.stderr)
    if args.out:
        out = Path(args.out)
    elif args.agent:
        from genesis_rl.adversaries import run_folder_of

        out = run_folder_of(Path(args.agent)) / "eval"
    else:
        raise UserInputError("--out is required when no --agent is given")
    from genesis_rl.core.files import output_folder

    with output_folder.hold(out):  # through the report, which writes into the folder as well
        summary = run_campaign(spec, out, force=args.force, resume=args.resume, progress=not args.quiet,
                               executor=executor)
        rule_metrics = [m for m in summary_rule_metrics(summary) if m != "total"]
        brief = {p: {**{m: None if (mean := s.metric(m).mean) is None else round(mean, 3) for m in rule_metrics},
                     "episodes_with_collision": s.episodes_with_collision,
                     "failure_modes": {k: v for k, v in s.failure_modes.items() if v}}
                 for p, s in summary.policies.items()}
        print(json.dumps({"out": str(out), "seconds": summary.run_seconds, "policies": brief}, indent=2))
        if not args.no_report:
            from genesis_rl.analysis.report import build_report

            print(f"report: {build_report(out, force=True)}")
    return 0
