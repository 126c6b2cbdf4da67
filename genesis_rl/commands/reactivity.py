"""``genesis-rl reactivity``: closed loop against open loop, does a policy react to the scene?"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from genesis_rl.commands.cli_args import count
from genesis_rl.core import limits


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``reactivity`` command's flags."""
    p = sub.add_parser("reactivity", help="closed-loop against open-loop: does a policy react to the scene?",
                       description="Play a campaign's step policy closed-loop on its scenes, then its action "
                       "sequences open-loop on the next scene (and on the same scene with another episode seed); "
                       "report the gaps (closed minus open) in return, collisions and collision violation with "
                       "bootstrap CIs and sign-flip p-values. A fixed schedule has no gap (docs/results/).")
    p.add_argument("--campaign", required=True, help="campaign folder (genesis-rl evaluate --out)")
    p.add_argument("--policy", default="agent", help="step policy of the campaign: agent (default), constant, "
                   "random, sunny or package.module:Class")
    p.add_argument("--scenes", type=int, default=None, help="the campaign's first N scenes (default: all)")
    p.add_argument("--no-other-seeds", action="store_true", help="skip the same-scene, other-seed comparison "
                   "(halves the cost: 2 episodes a scene instead of 4)")
    p.add_argument("--workers", type=int, action=count(1, limits.WORKERS), default=1,
                   help="parallel processes, one episode "
                   "each at a time (default: 1); the result is the same for any number")
    p.add_argument("--out", default=None, help="output JSON (default: CAMPAIGN/reactivity_POLICY.json)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.analysis.reactivity import measure_campaign
    from genesis_rl.campaigns.campaign_files import campaign_named_files
    from genesis_rl.core.files.output_paths import output_file

    out = output_file(args.out if args.out else Path(args.campaign) / f"reactivity_{args.policy}.json", args.force,
                      inputs=[args.campaign, *campaign_named_files(Path(args.campaign))],
                      products=[r"reactivity_[\w.-]*\.json"])
    t0 = time.perf_counter()
    result = measure_campaign(args.campaign, args.policy, args.scenes, not args.no_other_seeds,
                              progress=not args.quiet, workers=args.workers)
    data = {"campaign": str(args.campaign), "policy": args.policy, **result.to_json(),
            "seconds": round(time.perf_counter() - t0, 1)}
    out.write_json(data, indent=2)
    short = {kind: {m: {"gap": g["difference"]["mean"], "ci": [g["difference"]["ci_low"], g["difference"]["ci_high"]],
                        "p": g["p_value"]} for m, g in gaps.items()} for kind, gaps in data["gaps"].items()}
    print(json.dumps({"out": str(out), "policy": args.policy, "scenes": len(result.rows) // max(len(data["gaps"]), 1),
                      "gaps": short, "seconds": data["seconds"]}, indent=2), file=out.status)
    return 0
