"""``genesis-rl harden``: retrain a system's detector on the failures an attack found, re-test it on held-out
scenes and on clear-day frames, in rounds (docs/harden.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from genesis_rl.commands.cli_args import SEED, count
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError
from genesis_rl.harden.page import clear_text


def run(args: argparse.Namespace) -> int:
    from genesis_rl.core.files.output_paths import check_folder_output
    from genesis_rl.harden.rounds import HardenSpec, run_harden

    check_folder_output(args.out)
    finetune = {k: v for k, v in (("epochs", args.epochs), ("lr", args.lr), ("original_frames", args.original_frames),
                                  ("failure_repeat", args.failure_repeat),
                                  ("validation_frames", args.validation_frames), ("distill", args.distill))
                if v is not None}
    if args.keep_threshold:
        finetune["repick_threshold"] = False
    if finetune and args.retrain != "builtin":
        raise UserInputError("--epochs, --lr, --original-frames, --failure-repeat, --validation-frames, --distill "
                             f"and --keep-threshold set the built-in fine-tune; --retrain {args.retrain} takes none of "
                             "them")
    spec = HardenSpec(campaign=args.campaign, rounds=args.rounds, test_scenes=args.test_scenes,
                      attack_scenes=args.attack_scenes,
                      test_catalog_seed=args.test_catalog_seed, test_catalog=args.test_catalog, seed=args.seed,
                      retrain=args.retrain,
                      finetune=finetune, clear_frames=args.clear_frames, tolerance=args.tolerance,
                      adversary=args.adversary, member=args.member, estimate_episodes=args.estimate_episodes,
                      retest_scenes=args.retest_scenes, near_miss_ttc=args.near_miss_ttc)
    result = run_harden(spec, Path(args.out), workers=args.workers, force=args.force, resume=args.resume,
                        progress=not args.quiet)
    base = result["baseline"]["test"]["rate"]
    print(f"before: held-out in-ODD failure rate {base['rate']:.3f} ({base['k']}/{base['n']})")
    for rnd in result["rounds"]:
        test = rnd.get("test")
        rate = f"{test['rate']['rate']:.3f} ({test['rate']['k']}/{test['rate']['n']})" if test else "-"
        clear = rnd.get("clear")
        cl = f"; clear precision / recall {clear_text(clear)}" if clear else ""
        print(f"round {rnd['round']}: {rnd['status']}; attack found {rnd['attack']['in_odd_failures']} in-ODD "
              f"failure(s), {rnd['attack']['distinct']} distinct; held-out rate {rate}{cl}")
    final = result.get("final_attack")
    if final:
        print(f"re-attack of the hardened system: {final['in_odd_failures']} in-ODD failure(s), "
              f"{final['distinct']} distinct, in {final['episodes']} episodes")
    again = result.get("retrained_attack")
    if again:
        print(f"an agent re-trained against the hardened system: {again['in_odd_failures']} in-ODD failure(s), "
              f"{again['distinct']} distinct, in {again['episodes']} episodes")
    for when, est in (result.get("estimates") or {}).items():
        lo, hi = est["ci95"]
        print(f"in-ODD failure probability per episode under natural conditions, {when}: {est['probability']:.3g} "
              f"[{lo:.3g}, {hi:.3g}] ({est['failures']}/{est['episodes']})")
    retest = result.get("retest")
    if retest:
        for row in retest["rounds"]:
            rate = row["rate"]
            fell = f"; {row['fall']:.0%} below the accepted weights before it" if row.get("fall") is not None else ""
            print(f"re-test on {retest['scenes']} held-out scenes, round {row['round']} ({row['status']}): "
                  f"{rate['rate']:.3f} ({rate['k']}/{rate['n']}) [{rate['ci_low']:.3f}, {rate['ci_high']:.3f}]{fell}")
    if result.get("stopped"):
        print(f"stopped: {result['stopped']}")
    print(json.dumps({"out": args.out, "final_weights": result["final_weights"],
                      "final_weights_sha256": result["final_weights_sha256"]}))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("harden", help="retrain the system's detector on the failures found, re-test, in rounds",
                       description="Attack -> retrain -> re-test. Round 1 takes the in-ODD failures of CAMPAIGN "
                                   "(their frames up to the impact, with the simulator's labels), retrains the "
                                   "system's detector on them mixed with its own training data, and re-tests on "
                                   "held-out scenes and on clear-day frames (a round that lowers clear-day "
                                   "precision or recall by more than --tolerance is rejected). Later rounds re-run "
                                   "CAMPAIGN's adversaries against the hardened system. docs/harden.md")
    p.add_argument("campaign", help="the attack campaign folder (genesis-rl evaluate; one inside a benchmark run "
                                    "will do): its system, ODD, adversaries and steps are the ones hardened against")
    p.add_argument("--out", required=True, help="output folder: harden.json, harden.html, harden.png, round_N/")
    p.add_argument("--rounds", type=int, action=count(1, limits.ROUNDS), default=3,
                   help="rounds of attack -> retrain -> re-test (default 3)")
    p.add_argument("--test-scenes", type=int, action=count(1, limits.SCENES), default=20,
                   help="held-out scenes of every re-test (default 20)")
    p.add_argument("--attack-scenes", type=int, action=count(1, limits.SCENES), default=None,
                   help="scenes of the later rounds' attacks and the final one (default: the campaign's count); a "
                        "hardened system fails rarely, so what is left takes a bigger attack")
    p.add_argument("--test-catalog-seed", type=int, default=None,
                   help="the held-out scenes' catalog seed (default: the campaign's catalog seed + 1)")
    p.add_argument("--test-catalog", default=None, metavar="FILE",
                   help="a catalog file of held-out scenes (genesis-rl scenes; a CARLA town's) instead of a generated "
                        "one")
    p.add_argument("--retrain", default="builtin",
                   help="the retrain hook: builtin (fine-tune a genesis-rl detector checkpoint: systems builtin, "
                        "latency, adaptive; or coco's darknet model) or package.module:function (docs/harden.md)")
    p.add_argument("--epochs", type=int, default=None,
                   help="builtin fine-tune: epochs a round (default 4; coco 3)")
    p.add_argument("--lr", type=float, default=None,
                   help="builtin fine-tune: learning rate (default 5e-4; coco 1e-4)")
    p.add_argument("--original-frames", type=int, default=None,
                   help="builtin fine-tune: frames of the detector's own training data mixed in (default 800; "
                        "coco: 300 clear-day frames of the campaign's map)")
    p.add_argument("--failure-repeat", type=int, default=None,
                   help="builtin fine-tune: times each failure frame is seen an epoch (default 2)")
    p.add_argument("--validation-frames", type=int, default=None,
                   help="builtin fine-tune: frames of the detector's own validation data the score threshold is "
                        "re-picked on (best F1, as detector train picks it; default 480)")
    p.add_argument("--distill", type=float, default=None,
                   help="builtin fine-tune: weight of the distillation term that keeps the heatmap on the original "
                        "frames close to the starting weights' (learning without forgetting; default 5, coco 1; "
                        "0: off)")
    p.add_argument("--keep-threshold", action="store_true",
                   help="builtin fine-tune: keep the checkpoint's score threshold instead of re-picking it")
    p.add_argument("--clear-frames", type=int, action=count(1, limits.FRAMES), default=200,
                   help="clear-day evaluation frames on the campaign's map (default 200)")
    p.add_argument("--tolerance", type=float, default=0.01,
                   help="the largest clear-day precision or recall drop a round may cause (default 0.01)")
    p.add_argument("--adversary", default=None, metavar="CONFIG",
                   help="a train config (TOML, as genesis-rl train --config): after the last round an agent trained "
                        "by it against the hardened weights re-attacks them (the re-trained adversary)")
    p.add_argument("--member", default=None,
                   help="the zoo member whose system and ODD the campaign ran (genesis-rl zoo list): with "
                        "--estimate-episodes, its failure rate under natural conditions before and after")
    p.add_argument("--estimate-episodes", type=int, default=0,
                   help="crude Monte Carlo episodes of the in-ODD failure-rate estimate before the rounds and for "
                        "the final weights (default 0: none; genesis-rl estimate)")
    p.add_argument("--near-miss-ttc", type=float, default=1.5, metavar="SECONDS",
                   help="near misses join the data: collision-free episodes whose time to collision with the lead "
                        "fell to SECONDS or below inside the ODD, replayed from their records for their frames up "
                        "to the closest approach (default 1.5, the traffic-conflict line; 0: failures only)")
    p.add_argument("--retest-scenes", type=int, action=count(0, limits.SCENES), default=0,
                   help="after the rounds, re-test the weights before any round and every round's on this many "
                        "held-out scenes (the same for all; default 0: none). 20 scenes cannot tell a rate of 0.10 "
                        "from 0.05; may be added on --resume")
    p.add_argument("--seed", type=int, action=SEED, default=0, help="the retraining's draws flow from it (default 0)")
    p.add_argument("--workers", type=int, action=count(1, limits.WORKERS), default=1,
                   help="episode processes (results do not depend on it)")
    p.add_argument("--force", action="store_true", help="replace a hardening already in --out")
    p.add_argument("--resume", action="store_true", help="continue the hardening in --out where it stopped "
                                                         "(--rounds may grow; --retest-scenes, --adversary, "
                                                         "--member may be added)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
    return p
