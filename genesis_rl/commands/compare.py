"""``genesis-rl compare``: policies from different campaigns, paired scene by scene."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    pass



def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``compare`` command's flags."""
    p = sub.add_parser("compare", help="policies from different campaigns, paired scene by scene (Markdown)",
                       description="Compare policies evaluated in different campaigns (e.g. an agent in its own, the "
                                   "baselines in another) on the scenes they share: every policy's collisions, "
                                   "in-ODD collisions, distinct in-ODD failures, proximity violations and return, "
                                   "and the first policy's paired differences to each other one. The campaigns "
                                   "must share map, episode length, system, ODD, dynamics and episode seeds.")
    p.add_argument("series", nargs="+", help="LABEL=CAMPAIGN:POLICY, e.g. agent=runs/sac_s0/eval:agent; the first "
                                             "is compared with each other")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap resampling")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    p.add_argument("--force", action="store_true", help="overwrite an existing --json file")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.analysis.compare import compare, compare_markdown, parse_series
    from genesis_rl.campaigns.campaign_files import campaign_named_files
    from genesis_rl.core.files.output_paths import output_file

    series = [parse_series(s) for s in args.series]
    # checked before the campaigns are read: --json CAMP/campaign.json --force replaced a campaign's description;
    # what a campaign names (its agent run, catalog, env files) is an input too
    inputs: list[str | Path | None] = []
    for s in series:
        inputs += [s.folder, *campaign_named_files(s.folder)]
    out = output_file(args.json, args.force, flag="--json", inputs=inputs) if args.json else None
    result = compare(series, seed=args.seed)
    if out is not None:
        out.write_json(result, indent=1)
    print(compare_markdown(result), end="", file=out.status if out is not None else sys.stdout)
    return 0
