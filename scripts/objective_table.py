"""Score recorded campaigns under the paper's reward and the falsification objective (docs/adversaries.md).

    python scripts/objective_table.py CAMPAIGN_FOLDER [CAMPAIGN_FOLDER ...]

Prints a Markdown table (one row per episode) and, per objective, the chance that a failing episode returns more
than one without a failure.
"""

from __future__ import annotations

import sys
from pathlib import Path

from genesis_rl.analysis.objectives import score_campaign, separation
from genesis_rl.core.errors import UserInputError


def main(folders: list[str]) -> int:
    if not folders:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    try:
        episodes = [e for f in folders for e in score_campaign(Path(f))]
    except UserInputError as err:  # a missing or damaged campaign: one line, as the commands say it
        print(f"objective_table: error: {err}", file=sys.stderr)
        return err.exit_code
    print("| campaign | policy | scene | in-ODD failure | paper return | of it in contact | falsification return |")
    print("| --- | --- | ---: | --- | ---: | ---: | ---: |")
    for e in sorted(episodes, key=lambda e: (not e.failed, -e.paper)):
        print(f"| {e.campaign} | {e.policy} | {e.scene} | {'yes' if e.failed else 'no'} | {e.paper:.1f} | "
              f"{e.contact:.1f} | {e.falsification:.1f} |")
    for objective in ("paper", "falsification"):
        s = separation(episodes, objective)
        print(f"\n{objective}: P(a failing episode returns more than one without) = "
              f"{'n/a' if s is None else f'{s:.3f}'} ({sum(e.failed for e in episodes)} failing, "
              f"{sum(not e.failed for e in episodes)} not)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
