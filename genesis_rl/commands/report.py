"""``genesis-rl report``: report.html (or Markdown tables) for a campaign folder."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    pass



def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``report`` command's flags."""
    p = sub.add_parser("report", help="write report.html for a campaign folder")
    p.add_argument("campaign", help="campaign folder (genesis-rl evaluate --out)")
    p.add_argument("--out", default=None, help="report file (default: CAMPAIGN/report.html)")
    p.add_argument("--force", action="store_true", help="overwrite an existing report")
    p.add_argument("--markdown", action="store_true", help="print the summary tables as Markdown instead")
    p.add_argument("--scenarios", default=None,
                   help="an OpenSCENARIO export of this campaign (export --format openscenario --out DIR): each "
                        "failure links its .xosc and says whether it validated and replayed")
    p.add_argument("--estimate", default=None,
                   help="a genesis-rl estimate folder of the same system, ODD and map: the report states its "
                        "failure rate under natural conditions beside the failures found")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.analysis.report import build_report
    from genesis_rl.campaigns.summary import summarize_campaign, summary_markdown
    if args.markdown:
        print(summary_markdown(summarize_campaign(Path(args.campaign), write=False)), end="")
        return 0
    from genesis_rl.core.files.output_paths import is_stdout

    path = build_report(Path(args.campaign), args.out, force=args.force,
                        scenarios=Path(args.scenarios) if args.scenarios else None,
                        estimate=Path(args.estimate) if args.estimate else None)
    print(f"report: {path}", file=sys.stderr if is_stdout(args.out) else sys.stdout)
    return 0
