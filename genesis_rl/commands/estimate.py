"""``genesis-rl estimate``: how often a zoo member fails inside its ODD under natural conditions, by crude Monte
Carlo or by importance sampling with a cross-entropy-adapted proposal (docs/estimation.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from genesis_rl.commands.cli_args import SEED, count
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError


def run(args: argparse.Namespace) -> int:
    from genesis_rl.core.files.output_paths import check_folder_output
    from genesis_rl.estimation.nominal import load_starts
    from genesis_rl.estimation.run import EstimateSpec, run_estimate
    from genesis_rl.sut.zoo.members import zoo_member

    member = zoo_member(args.member)  # an unknown name is refused with the list
    check_folder_output(args.out)
    nominal = load_starts(Path(args.nominal)) if args.nominal else None
    if args.weights is not None and not Path(args.weights).exists():
        raise UserInputError(f"--weights '{args.weights}' does not exist")
    if args.weights is not None:
        from genesis_rl.sut.system.protocol import BUILTIN_SYSTEMS, WEIGHTED_SYSTEMS

        # refused here, not by the system's constructor after every episode's setup ran
        if member.system in BUILTIN_SYSTEMS and member.system not in WEIGHTED_SYSTEMS:
            raise UserInputError(f"--weights '{args.weights}': member '{args.member}' runs system '{member.system}', "
                                 f"which takes no weights; --weights applies to members whose system is one of "
                                 f"{', '.join(WEIGHTED_SYSTEMS)}")
    spec = EstimateSpec(member=args.member, method=args.method, episodes=args.episodes, seed=args.seed,
                        steps=args.steps, stages=args.stages if args.method == "importance" else 1,
                        defensive=args.defensive, elite=args.elite, pilot=args.pilot, nominal=nominal,
                        elite_min=args.elite_min, smoothing=args.smoothing, score=args.score,
                        tilt=tuple(t for t in args.tilt.split(",") if t) if args.tilt else None,
                        weights=args.weights, estimate_from=args.estimate_from)
    result = run_estimate(spec, Path(args.out), workers=args.workers, force=args.force, resume=args.resume,
                          progress=not args.quiet)
    est = result["estimate"]
    lo, hi = est["ci95"]
    print(f"{args.member}: in-ODD failure probability per {result['episode_s']:g} s episode "
          f"{est['probability']:.3g} [95 % CI {lo:.3g}, {hi:.3g}] from {est['episodes']} episodes "
          f"({est['failures']} failed; {args.method}; {result['episodes_spent']} played in all); per hour driven "
          f"{result['per_hour']:.3g}")
    for w in est["warnings"]:
        print(f"warning: {w}")
    for c in result["clusters"][:5]:
        print(f"  {c['share']:.0%} of it: {c['cluster']} ({c['failures']} failure(s))")
    print(json.dumps({"out": args.out, "probability": est["probability"], "ci95": est["ci95"],
                      "episodes": est["episodes"], "failures": est["failures"], "ess": est["ess"]}))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("estimate", help="how often a zoo member fails inside its ODD under natural conditions "
                                        "(crude Monte Carlo or importance sampling)")
    p.add_argument("--member", required=True, help="the zoo member (genesis-rl zoo list)")
    p.add_argument("--method", default="importance", choices=["crude", "importance"],
                   help="crude: episodes drawn from the nominal model; importance: from a cross-entropy-adapted "
                        "start proposal with a defensive share of nominal starts, weighted (default)")
    p.add_argument("--episodes", type=int, action=count(1, limits.SCENES), default=120,
                   help="episodes in all (default 120)")
    p.add_argument("--stages", type=int, default=4,
                   help="importance: stages; all but the last adapt the proposal by cross-entropy (default 4)")
    p.add_argument("--pilot", type=float, default=0.5,
                   help="importance: the share of the episodes the pilot stages take to adapt the proposal "
                        "(default 0.5; see --estimate-from)")
    p.add_argument("--defensive", type=float, default=0.2,
                   help="importance: the share of nominal starts in every proposal (default 0.2; bounds each "
                        "weight by 1/share)")
    p.add_argument("--elite", type=float, default=0.2,
                   help="importance: the share of a stage, highest scores first, that refits the proposal "
                        "(default 0.2; every failure is in it)")
    p.add_argument("--elite-min", type=int, default=5,
                   help="importance: the fewest episodes that refit the proposal (default 5)")
    p.add_argument("--smoothing", type=float, default=1.0,
                   help="importance: the refit's weight against the proposal before, the rest kept (default 1: the "
                        "refit alone; Rubinstein and Kroese advise 0.4-0.9 where pilot stages are small)")
    p.add_argument("--tilt", default=None,
                   help="importance: the start variables the proposal tilts, comma-separated (e.g. "
                        "lead_brake_onset_s,lead_brake_decel); the rest keep the nominal model (default: every one)")
    p.add_argument("--score", default="danger", choices=["danger", "reward"],
                   help="importance: what ranks the episodes that did not fail: danger, the largest inverse "
                        "time-to-collision to the lead (default), or reward, the episode's summed reward (before 0.26)")
    p.add_argument("--estimate-from", default="last", choices=["last", "adapted"],
                   help="importance: which stages' episodes make the estimate: last, the last stage alone "
                        "(default), or adapted, every stage after the first (broad) pilot, pooled with fixed "
                        "weights (unbiased; better where the failure is an event's tail, docs/estimation.md); "
                        "a resumed estimate may change it (the same episodes, read again)")
    p.add_argument("--steps", type=int, action=count(1, limits.SIM_STEPS), default=None,
                   help="steps per episode (default: the member's)")
    p.add_argument("--nominal", default=None,
                   help="a TOML file of start ranges replacing the default nominal model (docs/estimation.md)")
    p.add_argument("--weights", default=None,
                   help="the member's system with these detector weights (a hardened one: genesis-rl harden); "
                        "default: the member's own")
    p.add_argument("--seed", type=int, action=SEED, default=0, help="every draw flows from it (default 0)")
    p.add_argument("--workers", type=int, action=count(1, limits.WORKERS), default=1,
                   help="episode processes (results do not depend on it)")
    p.add_argument("--out", required=True, help="output folder: episodes.csv, estimate.json, estimate.png")
    p.add_argument("--force", action="store_true", help="replace an estimate already in --out")
    p.add_argument("--resume", action="store_true",
                   help="continue the estimate in --out where it stopped (crude Monte Carlo may change --episodes: "
                        "it goes on to more, or reports the first N)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p
