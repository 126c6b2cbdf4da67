"""Per-scene returns of several policies from campaign folders (docs/results.md section 7's figure).

    python scripts/plot_policy_returns.py --out docs/images/reactive_returns.png \
        agent=runs/reactive_s0/eval:agent agent_long=runs/reactive_long/eval:agent \
        random=runs/reactive_s0/eval:random constant=runs/reactive_s0/eval:constant \
        cem=runs/reactive_s0/eval:cem cmaes=runs/reactive_s0/eval:cmaes
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("series", nargs="+", help="LABEL=CAMPAIGN:POLICY")
    args = ap.parse_args()
    data = {}
    for item in args.series:
        label, rest = item.split("=", 1)
        folder, policy = rest.rsplit(":", 1)
        rows = [json.loads(p.read_text()) for p in sorted((Path(folder) / "episodes" / policy).glob("*.json"))]
        data[label] = {r["scene"]: r["return"] for r in rows}
    scenes = sorted(next(iter(data.values())))
    fig, ax = plt.subplots(figsize=(10, 4.2))
    width = 0.8 / len(data)
    for k, (label, returns) in enumerate(data.items()):
        ax.bar(np.arange(len(scenes)) + (k - (len(data) - 1) / 2) * width, [returns[s] for s in scenes], width,
               label=f"{label} (mean {np.mean(list(returns.values())):.0f})")
    ax.set_xticks(np.arange(len(scenes)), [str(s) for s in scenes])
    ax.set_xlabel("highway test scene")
    ax.set_ylabel("episode return (the agent's objective)")
    ax.set_ylim(200, None)
    ax.legend(fontsize=8, ncol=3, loc="upper left")
    ax.set_title("inside urban_all_day, natural dynamics: per-scene return of each policy")
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)


if __name__ == "__main__":
    main()
