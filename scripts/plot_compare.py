"""Plot a `genesis-rl compare --json` result: each policy's return (mean, 95% CI, every scene as a dot) beside
its episodes with an in-ODD collision and with a proximity violation, and the simulator steps it spent.

    genesis-rl compare agent_s0=runs/sac_s0/eval:agent ... --json runs/protocol.json
    python scripts/plot_compare.py runs/protocol.json --out docs/images/protocol.png \
        --title "50 highway scenes inside urban_all_day, natural weather"
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
    ap.add_argument("compare_json")
    ap.add_argument("--out", required=True)
    ap.add_argument("--title", default="")
    args = ap.parse_args()
    result = json.loads(Path(args.compare_json).read_text())
    policies = result["policies"]
    labels = list(policies)
    n = len(result["scenes"])
    fig, (ax_r, ax_f) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [3, 2]})
    x = np.arange(len(labels))
    for i, label in enumerate(labels):
        p = policies[label]
        r = p["return"]
        ax_r.errorbar(i, r["mean"], yerr=[[r["mean"] - r["ci_low"]], [r["ci_high"] - r["mean"]]], fmt="o",
                      color="black", capsize=5, zorder=3)
        if "returns" in p:
            ax_r.scatter(i + np.linspace(-0.25, 0.25, len(p["returns"])), p["returns"], s=8, alpha=0.4)
    ax_r.set_xticks(x, [f"{lb}\n{policies[lb]['sim_steps'] / n:,.0f}\nsteps/scene" for lb in labels], fontsize=8)
    ax_r.set_ylabel("episode return (mean, 95% CI)")
    ax_r.set_title("the agents' objective")
    width = 0.38
    ax_f.bar(x - width / 2, [policies[lb]["in_odd_collisions"] for lb in labels], width, label="in-ODD collision")
    ax_f.bar(x + width / 2, [policies[lb]["proximity_episodes"] for lb in labels], width,
             label="proximity violation")
    ax_f.set_xticks(x, labels, fontsize=8, rotation=30, ha="right")
    ax_f.set_ylabel(f"episodes (of {n})")
    ax_f.set_ylim(0, max(3, *(policies[lb]["proximity_episodes"] for lb in labels)) + 1)
    ax_f.yaxis.get_major_locator().set_params(integer=True)
    ax_f.legend(fontsize=8)
    ax_f.set_title("failures")
    if args.title:
        fig.suptitle(args.title)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == "__main__":
    main()
