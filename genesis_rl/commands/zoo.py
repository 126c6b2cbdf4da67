"""``genesis-rl zoo``: the systems under test with known weaknesses (``zoo list``) and the sweep that measures a
member's ground truth, its failure rate inside its trigger region and around it (``zoo sweep``)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from genesis_rl.commands.cli_args import count
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError


def _values(text: str, flag: str = "--values") -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise UserInputError(f"{flag} '{text}': give a comma list of numbers, e.g. 0,5,10,14,20,40") from None


def _hold(text: str | None) -> tuple[tuple[str, float], ...]:
    """``--hold lead_decel=6,fog_density=51``: knob=value pairs held for every swept value."""
    if not text:
        return ()
    pairs = []
    for part in text.split(","):
        key, sep, value = part.partition("=")
        try:
            if not sep:
                raise ValueError
            pairs.append((key.strip(), float(value)))
        except ValueError:
            raise UserInputError(f"--hold '{text}': give knob=value pairs, e.g. lead_decel=6,fog_density=51") from None
    return tuple(pairs)


def print_members() -> None:
    """Every zoo member: name, kind, map, system, ODD, traffic (when not mixed), trigger region, summary
    (``zoo list`` and ``benchmark --list``)."""
    from genesis_rl.sut.zoo.members import ZOO

    for name, m in ZOO.items():
        traffic = f", traffic {m.traffic}" if m.traffic != "mixed" else ""
        print(f"{name} ({m.kind}, {m.map}, system {m.system}, ODD {m.odd}{traffic}); trigger region: "
              f"{m.trigger.describe()}\n"
              f"  {m.summary}")


def _list(args: argparse.Namespace) -> int:
    print_members()
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from genesis_rl.benchmark.sweep import SweepSpec, run_sweep
    from genesis_rl.core.files.output_paths import check_folder_output

    spec = SweepSpec(member=args.member, knob=args.knob, values=_values(args.values), scenes=args.scenes,
                     seed=args.seed, steps=args.steps, hold=_hold(args.hold))
    check_folder_output(args.out)
    table = run_sweep(spec, Path(args.out), force=args.force, resume=args.resume, workers=args.workers,
                      progress=not args.quiet)
    weakness = table["member_kind"] == "weakness"
    places = {True: "in the region", False: "outside the region",
              None: "the region decided per step" if weakness else "no region"}
    for r in table["rows"]:
        where = places[r["in_region"]]
        if not r["inside_odd"]:
            print(f"{spec.knob} = {r['value']:g}: outside the member's ODD, not driven")
            continue
        lo, hi = r["ci95"]
        reached = f"; {r['reached']} reached the region" if weakness else ""
        print(f"{spec.knob} = {r['value']:g} ({where}): {r['failed']}/{r['trials']} episodes with an in-ODD failure "
              f"[95 % CI {lo:.2f}-{hi:.2f}]{reached}")
    keys = ("inside_region", "outside_region", "driven", "reached_region", "never_reached")
    print(json.dumps({"out": args.out, **{k: table[k] for k in keys if k in table}}))
    print(f"plot: {Path(args.out) / 'sweep.png'}")
    return 0


def _truth(args: argparse.Namespace) -> int:
    from genesis_rl.benchmark.reactive_truth import measure, plot_truth
    from genesis_rl.core.files.io_utils import atomic_write_json, ensure_writable
    from genesis_rl.core.files.output_paths import output_file

    limits.SCENES.check(args.tuning + args.held_out, "--tuning + --held-out")
    from genesis_rl.benchmark.reactive_truth import WATCHERS

    if args.member not in WATCHERS:
        raise UserInputError(f"zoo member '{args.member}' has no scripted reactive policy; allowed: "
                             f"{', '.join(WATCHERS)}")
    if not args.out.endswith(".json"):
        raise UserInputError(f"--out '{args.out}': give a .json file (the plot goes beside it, .png)")
    out = output_file(args.out, args.force)
    picture = Path(args.out).with_suffix(".png")
    ensure_writable(picture, args.force)
    onsets = _values(args.onsets, "--onsets") if args.onsets else ()
    if not all(math.isfinite(t) and t >= 0.0 for t in onsets):  # before the pool starts, not in a worker
        raise UserInputError(f"--onsets '{args.onsets}': every onset must be a finite number of seconds >= 0")
    # every onset is a schedule played on each tuning scene: their count is a search budget
    limits.SEARCH_BUDGET.check(len(onsets), "--onsets")
    result = measure(args.member, tuning=args.tuning, held_out=args.held_out, onsets=onsets, seed=args.seed,
                     workers=args.workers, progress=not args.quiet)
    assert out.path is not None
    atomic_write_json(out.path, result, indent=1)
    plot_truth(result, picture)
    for name in ("reactive", "best_fixed"):
        cell = result[name]
        lo, hi = cell["ci95"]
        print(f"{name}: {cell['counted']}/{cell['episodes']} held-out episodes counted (triggered and avoidable) "
              f"[95 % CI {lo:.2f}-{hi:.2f}]; {cell['failed']} failed, {cell['triggered']} triggered, "
              f"{cell['unavoidable']} blamed unavoidable")
    print(json.dumps({"out": args.out, "best_fixed_onset_s": result["best_fixed_onset_s"],
                      "passes": result["passes"], "plot": str(picture)}))
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from genesis_rl.commands.cli_args import SEED

    zp = subparsers.add_parser("zoo", help="systems under test with known in-ODD weaknesses; sweep their ground truth")
    zsub = zp.add_subparsers(dest="zoo_command", required=True)
    ls = zsub.add_parser("list", help="the members, their trigger regions and what they are")
    ls.set_defaults(func=run)
    sw = zsub.add_parser(
        "sweep", help="a member's failure rate with one knob held at each value, inside its trigger region and around",
        description="For each value, a campaign of the sunny policy (the weather held) on the member's system, map, "
                    "ODD and env, starting with KNOB at the value; in-ODD failures counted as the benchmark counts "
                    "them, with exact 95 %% intervals; sweep.json and sweep.png (docs/zoo.md).")
    sw.add_argument("member", help="zoo member (genesis-rl zoo list)")
    sw.add_argument("--knob", required=True, help="the knob to hold at each value, e.g. sun_altitude_angle")
    sw.add_argument("--values", required=True, help="comma list of values in the knob's unit, e.g. 2,5,10,14,20,40")
    sw.add_argument("--hold", default=None,
                    help="other knobs held at one value for every swept value, e.g. lead_decel=6 (a region over two "
                         "knobs: sweep one, hold the other inside it)")
    sw.add_argument("--scenes", type=int, action=count(1, limits.SCENES), default=8,
                    help="scenes (episodes) per value (default 8)")
    sw.add_argument("--seed", type=int, action=SEED, default=0, help="campaign seed: which scenes and episode seeds")
    sw.add_argument("--steps", type=int, action=count(1, limits.SIM_STEPS), default=None,
                    help="steps per episode (default: the member's own)")
    sw.add_argument("--workers", type=int, action=count(1, limits.WORKERS), default=1, help="parallel episodes")
    sw.add_argument("--out", required=True, help="sweep folder")
    sw.add_argument("--resume", action="store_true", help="continue the sweep in --out where it stopped")
    sw.add_argument("--force", action="store_true", help="replace an existing sweep folder")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.set_defaults(func=run)
    tr = zsub.add_parser(
        "truth", help="a reactive member's ground truth: its scripted reactive policy against the best fixed schedule",
        description="On held-out scenes and world seeds, the member's scripted reactive policy (stall_watcher on "
                    "stall_braking) against the best fixed schedule (the lead braking from one onset), searched "
                    "over an onset grid on tuning scenes with their own world seeds. The member is reactive when "
                    "the first triggers it in >= 60 % of held-out episodes and the second in <= 15 %. Writes "
                    "FILE.json and FILE.png (docs/zoo.md).")
    tr.add_argument("member", help="a reactive zoo member: stall_braking")
    tr.add_argument("--tuning", type=int, action=count(1), default=4,
                    help="tuning scenes each fixed onset is played on (default 4)")
    tr.add_argument("--held-out", type=int, action=count(1), default=30,
                    help="held-out scenes both policies play (default 30)")
    tr.add_argument("--onsets", default=None,
                    help="comma list of fixed onsets [s] to search (default every second of the episode but "
                         "its last 4)")
    tr.add_argument("--seed", type=int, action=SEED, default=0, help="catalog seed and the source of the world seeds")
    tr.add_argument("--workers", type=int, action=count(1, limits.WORKERS), default=1, help="parallel episodes")
    tr.add_argument("--out", required=True, help="result file, .json (the plot beside it, .png)")
    tr.add_argument("--force", action="store_true", help="replace an existing result")
    tr.add_argument("--quiet", action="store_true", help="no progress bar")
    tr.set_defaults(func=run)
    return zp


def run(args: argparse.Namespace) -> int:
    return {"list": _list, "sweep": _sweep, "truth": _truth}[args.zoo_command](args)
