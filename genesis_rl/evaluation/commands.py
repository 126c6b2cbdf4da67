"""``genesis-rl evaluate | report | replay`` (``export`` is ``export_cmd``, above this package).

Each subcommand imports what it runs inside its handler (local imports on purpose): ``genesis-rl --help`` and
a mistyped flag answer in 0.45 s instead of 3.2 s (what importing torch, Panda3D and the campaign code costs)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from genesis_rl import limits
from genesis_rl.backends import add_backend_arguments, check_backend_setting, env_overrides_from_args
from genesis_rl.cli_args import add_odd_arguments, add_scale_arguments, odd_overrides_from_args
from genesis_rl.errors import UserInputError
from genesis_rl.evaluation.summary import summary_rule_metrics
from genesis_rl.scenes.placement import TRAFFIC

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
    from genesis_rl.backends import servers_text
    from genesis_rl.distributed.servers import parse_servers, servers_for_workers
    from genesis_rl.distributed.settings import ExecutorSettings

    servers = servers_for_workers(backend, parse_servers(servers_text(args)), args.workers)
    return ExecutorSettings(kind=args.executor, workers=args.workers, ray_address=args.ray_address,
                            servers=tuple(servers))


def _cmd_evaluate(args: argparse.Namespace) -> int:
    # counts first, before any policy is imported: a refused budget answers at once
    for flag in ("seed", "catalog_seed"):
        if getattr(args, flag) < 0:
            raise UserInputError(f"--{flag.replace('_', '-')} = {getattr(args, flag)} must be >= 0")
    if args.retries < 0:
        raise UserInputError(f"--retries = {args.retries} must be >= 0")
    limits.RETRIES.check(args.retries, "--retries")
    if args.workers < 1:
        raise UserInputError(f"--workers = {args.workers} must be >= 1")
    limits.WORKERS.check(args.workers, "--workers")
    limits.SCENES.check(args.scenes, "--scenes")
    if args.steps < 1:
        raise UserInputError(f"--steps = {args.steps} must be >= 1")
    limits.SIM_STEPS.check(args.steps, "--steps")  # as drive --steps: 999999999 ran for days
    if args.search_segments < 1:
        raise UserInputError(f"--search-segments = {args.search_segments} must be >= 1")
    if args.search_budget < 2:
        raise UserInputError(f"--search-budget = {args.search_budget} must be >= 2 episodes")
    limits.SEARCH_BUDGET.check(args.search_budget, "--search-budget")  # 1000000000 would search for years
    if args.search_segments > args.steps:
        raise UserInputError(f"--search-segments = {args.search_segments} must be at most --steps = {args.steps} "
                             "(a segment is at least one step)")
    from genesis_rl.adversaries import resolve_policy
    from genesis_rl.evaluation.campaign import CampaignSpec, env_settings_for, run_campaign
    from genesis_rl.evaluation.campaign_spec import campaign_map

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
    from genesis_rl import output_folder

    with output_folder.hold(out):  # through the report, which writes into the folder as well
        summary = run_campaign(spec, out, force=args.force, resume=args.resume, progress=not args.quiet,
                               executor=executor)
        rule_metrics = [m for m in summary_rule_metrics(summary) if m != "total"]
        brief = {p: {**{m: None if s[m]["mean"] is None else round(s[m]["mean"], 3) for m in rule_metrics},
                     "episodes_with_collision": s["episodes_with_collision"],
                     "failure_modes": {k: v for k, v in s["failure_modes"].items() if v}}
                 for p, s in summary["policies"].items()}
        print(json.dumps({"out": str(out), "seconds": summary["run_seconds"], "policies": brief}, indent=2))
        if not args.no_report:
            from genesis_rl.evaluation.report import build_report

            print(f"report: {build_report(out, force=True)}")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from genesis_rl.evaluation.report import build_report
    from genesis_rl.evaluation.summary import summarize_campaign, summary_markdown
    if args.markdown:
        print(summary_markdown(summarize_campaign(Path(args.campaign), write=False)), end="")
        return 0
    from genesis_rl.output_paths import is_stdout

    path = build_report(Path(args.campaign), args.out, force=args.force,
                        scenarios=Path(args.scenarios) if args.scenarios else None,
                        estimate=Path(args.estimate) if args.estimate else None)
    print(f"report: {path}", file=sys.stderr if is_stdout(args.out) else sys.stdout)
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from genesis_rl.evaluation.compare import compare, compare_markdown, parse_series
    from genesis_rl.output_paths import output_file

    series = [parse_series(s) for s in args.series]
    # checked before the campaigns are read: --json CAMP/campaign.json --force replaced a campaign's description
    out = output_file(args.json, args.force, flag="--json", inputs=[s.folder for s in series]) if args.json else None
    result = compare(series, seed=args.seed)
    if out is not None:
        out.write_json(result, indent=1)
    print(compare_markdown(result), end="", file=out.status if out is not None else sys.stdout)
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from genesis_rl.drive import write_telemetry
    from genesis_rl.evaluation.records import load_record, replay_record
    from genesis_rl.io_utils import atomic_write_json, ensure_writable
    from genesis_rl.viz.frames import annotate_frame, write_gif

    if args.gif_seconds is not None and args.gif_seconds < 0:
        raise UserInputError(f"--gif-seconds must be >= 0, got {args.gif_seconds}")
    rec = load_record(args.record)
    spec = str(rec["system"].get("spec", ""))
    if args.weights and spec in ("blind", "oracle"):  # they read no weights; a plug-in may
        raise UserInputError(f"--weights applies to records of --system builtin, yolo or a plug-in that takes "
                             f"weights; this record's system is '{spec}'")
    from genesis_rl.output_paths import check_folder_output, check_inputs

    out = Path(args.out)
    check_folder_output(args.out)
    names = ("replay.json", "telemetry.parquet", "replay.gif")
    check_inputs(out, [args.record, args.weights], folder=True, files=names)
    for name in names:
        ensure_writable(out / name, args.force)
    result = replay_record(rec, weights=args.weights, progress=not args.quiet, keep_frames=not args.no_gif)
    write_telemetry(out / "telemetry.parquet", result["records"])
    if not args.no_gif:
        hit = next((i for i, r in enumerate(result["records"]) if r.collision.collided), len(result["records"]) - 1)
        lo = max(0, hit - args.gif_seconds * 20) if args.gif_seconds else 0
        frames = [annotate_frame(result["frames"][i], result["records"][i])
                  for i in range(lo, min(len(result["frames"]), hit + 20), 2)]
        write_gif(out / "replay.gif", frames, fps=10)
    report = {"record": str(args.record), "reproduced": result["reproduced"],
              "steps_identical": result["steps_identical"], "violations": result["violations"],
              "render_version": result["render_version"],
              "recorded_render_version": result["recorded_render_version"],
              "recorded_violations": result["recorded_violations"], "steps": len(result["records"]),
              "first_collision_step": next((r.step for r in result["records"] if r.collision.collided), None)}
    atomic_write_json(out / "replay.json", report, indent=2)
    print(json.dumps(report, indent=2))
    if not result["reproduced"]:
        same_violations = set(result["violations"]) == set(result["recorded_violations"]) and all(
            math.isclose(result["violations"][k], v, rel_tol=1e-9, abs_tol=1e-9)
            for k, v in result["recorded_violations"].items())
        if same_violations:
            print("genesis-rl replay: the violations are the recorded ones, but the per-step telemetry is not "
                  "(its digest differs: a detection score or distance changed somewhere)", flush=True)
            _explain_platform(result["recorded_platform"], result["platform"])
        else:
            print("genesis-rl replay: the replayed violations differ from the recorded ones", flush=True)
        from genesis_rl import __version__

        recorded_version = rec.get("package_version")
        if result["recorded_render_version"] != result["render_version"]:
            print(f"genesis-rl replay: the record was made by lite renderer version "
                  f"{result['recorded_render_version']} (genesis-rl {recorded_version}), this is "
                  f"version {result['render_version']}: the frames differ slightly, so the detector may "
                  f"see the scene differently; replay with the recorded genesis-rl version to reproduce it",
                  flush=True)
        elif recorded_version != __version__:
            print(f"genesis-rl replay: the record was made by genesis-rl {recorded_version}, this is "
                  f"{__version__}; replay it with the recorded version to reproduce it exactly", flush=True)
        return 1
    return 0


def _explain_platform(recorded: dict | None, now: dict) -> None:
    """Say when the record was made where float math differs in its last bits (provenance.numeric_platform)."""
    if recorded is None:
        print("genesis-rl replay: the record does not name the machine that made it (records before genesis-rl "
              "0.8.0); a CPU with other vector extensions (AVX2 against AVX-512) or another numpy or torch "
              f"differs in the last bits of float math; this machine: {now}", flush=True)
    elif recorded != now:
        diff = {k: (recorded.get(k), v) for k, v in now.items() if recorded.get(k) != v}
        print("genesis-rl replay: the record was made on a machine whose float math differs in its last bits "
              f"from this one's (recorded, here): {diff}; replay it on such a machine to reproduce it bit for "
              "bit", flush=True)


def add_evaluation_commands(sub: argparse._SubParsersAction) -> None:
    ev = sub.add_parser("evaluate", help="evaluation campaign: weather policies on held-out scenes; summary, report")
    ev.add_argument("--agent", default=None, help="trained run folder (runs/NAME) or agent .zip")
    ev.add_argument("--policies", default="sunny,random,agent",
                    help="comma list: sunny, random, constant, agent, cmaes, cem (search baselines) or "
                         "package.module:Class")
    ev.add_argument("--map", default=None, help="test map (default: the --catalog's map, else highway; the agent "
                                                "trains on urban)")
    ev.add_argument("--catalog", default=None, help="test catalog file (default: the map's generated catalog)")
    ev.add_argument("--catalog-seed", type=int, default=0, help="seed of the generated test catalog")
    ev.add_argument("--traffic", default="mixed", choices=TRAFFIC,
                    help="traffic of the generated test catalog: mixed (default, the paper's: the lead stops now "
                         "and then) or free_flow (lite; everyone cruises near the limit, nobody stops on its own)")
    ev.add_argument("--scenes", type=int, default=50, help="scenes picked from the catalog by --seed")
    ev.add_argument("--seed", type=int, default=0, help="campaign seed: scene choice and episode seeds")
    ev.add_argument("--steps", type=int, default=512, help="steps per episode (0.05 s each)")
    ev.add_argument("--system", default=None, help="system under test (default: the agent's)")
    ev.add_argument("--weights", default=None,
                    help="detector weights of the system under test (builtin or yolo; default: the shipped ones; "
                         "coco: a model folder): "
                         "an agent against a detector it never trained with")
    ev.add_argument("--config", default=None, help="TOML with an [env] table, when no --agent is given")
    ev.add_argument("--search-budget", type=int, default=8, help="episodes per scene a search baseline may spend")
    ev.add_argument("--search-segments", type=int, default=4, help="piecewise-constant segments of a searched schedule")
    ev.add_argument("--constant-action", default=None, metavar="A,B,...",
                    help="policy 'constant': its action, one value in [-1, 1] per knob (default: 1 on every knob)")
    ev.add_argument("--start", default="fixed", choices=["fixed", "natural"],
                    help="where episodes start: fixed (the start weather, default) or natural (each policy chooses "
                         "the knobs that cannot move within an episode, the sun under natural dynamics: random "
                         "draws them inside the ODD, constant takes its corner, the searches search them)")
    ev.add_argument("--records", default="failures", choices=["failures", "all"],
                    help="write replayable edge-case records for failing episodes only, or for all")
    ev.add_argument("--retries", type=int, default=2,
                    help="times an episode is retried after reconnecting when the simulator dies mid-episode")
    ev.add_argument("--workers", type=int, default=1,
                    help="parallel workers (processes, or Ray actors with --executor ray), one episode each at a time")
    add_scale_arguments(ev, "--workers")
    ev.add_argument("--out", default=None, help="campaign folder (default: AGENT/eval)")
    ev.add_argument("--resume", action="store_true", help="continue an interrupted campaign in --out")
    ev.add_argument("--force", action="store_true", help="replace an existing campaign folder")
    ev.add_argument("--no-report", action="store_true", help="skip report.html")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    add_odd_arguments(ev)
    ev.add_argument("--no-counterfactual", action="store_true",
                    help="skip the oracle replay of each collision (by default on with an ODD): blame then rests "
                         "on the visibility evidence alone")
    add_backend_arguments(ev, default=None)
    ev.set_defaults(func=_cmd_evaluate)

    rp = sub.add_parser("report", help="write report.html for a campaign folder")
    rp.add_argument("campaign", help="campaign folder (genesis-rl evaluate --out)")
    rp.add_argument("--out", default=None, help="report file (default: CAMPAIGN/report.html)")
    rp.add_argument("--force", action="store_true", help="overwrite an existing report")
    rp.add_argument("--markdown", action="store_true", help="print the summary tables as Markdown instead")
    rp.add_argument("--scenarios", default=None,
                    help="an OpenSCENARIO export of this campaign (export --format openscenario --out DIR): each "
                         "failure links its .xosc and says whether it validated and replayed")
    rp.add_argument("--estimate", default=None,
                    help="a genesis-rl estimate folder of the same system, ODD and map: the report states its "
                         "failure rate under natural conditions beside the failures found")
    rp.set_defaults(func=_cmd_report)

    cp = sub.add_parser("compare", help="policies from different campaigns, paired scene by scene (Markdown)",
                        description="Compare policies evaluated in different campaigns (e.g. an agent in its own, the "
                                    "baselines in another) on the scenes they share: every policy's collisions, "
                                    "in-ODD collisions, distinct in-ODD failures, proximity violations and return, "
                                    "and the first policy's paired differences to each other one. The campaigns "
                                    "must share map, episode length, system, ODD, dynamics and episode seeds.")
    cp.add_argument("series", nargs="+", help="LABEL=CAMPAIGN:POLICY, e.g. agent=runs/sac_s0/eval:agent; the first "
                                              "is compared with each other")
    cp.add_argument("--seed", type=int, default=0, help="seed of the bootstrap resampling")
    cp.add_argument("--json", default=None, help="also write the figures to this JSON file")
    cp.add_argument("--force", action="store_true", help="overwrite an existing --json file")
    cp.set_defaults(func=_cmd_compare)

    rl = sub.add_parser("replay", help="re-run an edge-case record; check its violations; write a GIF")
    rl.add_argument("record", help="edge-case record (CAMPAIGN/records/*.json)")
    rl.add_argument("--out", required=True, help="output directory")
    rl.add_argument("--weights", default=None, help="detector weights, when the recorded file has moved")
    rl.add_argument("--gif-seconds", type=int, default=6, help="seconds before the collision in the GIF (0: all)")
    rl.add_argument("--no-gif", action="store_true", help="skip the animation")
    rl.add_argument("--force", action="store_true", help="overwrite existing outputs")
    rl.add_argument("--quiet", action="store_true", help="no progress bar")
    rl.set_defaults(func=_cmd_replay)

