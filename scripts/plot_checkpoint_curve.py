"""Plot docs/images/results_checkpoint_curve.png from the checkpoint campaigns of docs/results.md, section 1.

Run from the repository root after the commands listed there: ``python scripts/plot_checkpoint_curve.py``.
"""

import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = pathlib.Path("runs/paper/curve")
METRICS = [
    ("collision", "collision violation [m/s]"),
    ("rss_deficit", "RSS deficit / episode [m]"),
    ("episodes_with_collision", "episodes with a collision (of 8)"),
    ("mean_iou", "mean IoU"),
]


def _value(stats: dict, key: str) -> float:
    v = stats[key]
    return v["mean"] if isinstance(v, dict) else v


def main() -> None:
    steps, rows = [], []
    for d in sorted(ROOT.glob("step_*")):
        steps.append(int(d.name.split("_")[1]))
        rows.append(json.loads((d / "summary.json").read_text())["policies"]["agent"])
    base = json.loads((ROOT / "baselines" / "summary.json").read_text())["policies"]
    fig, axes = plt.subplots(1, 4, figsize=(17, 3.6))
    for ax, (key, title) in zip(axes, METRICS, strict=True):
        if isinstance(rows[0][key], dict):
            lo = [r[key]["ci_low"] for r in rows]
            hi = [r[key]["ci_high"] for r in rows]
            ax.fill_between(steps, lo, hi, color="#c0392b", alpha=0.15, lw=0)
        ax.plot(steps, [_value(r, key) for r in rows], "o-", color="#c0392b",
                label="agent (deterministic checkpoint)")
        for pol, col in (("sunny", "#f39c12"), ("random", "#7f8c8d")):
            ax.axhline(_value(base[pol], key), color=col, ls="--", label=pol)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("training steps")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower right")
    fig.suptitle("runs/paper checkpoints (step 0: the untrained policy, seed 0) played deterministically on 8 urban "
                 "scenes (campaign seed 1), 512 steps each; band: bootstrap 95% CI", fontsize=10)
    fig.tight_layout()
    fig.savefig("docs/images/results_checkpoint_curve.png", dpi=100)
    for st, r in zip(steps, rows, strict=True):
        print(st, *(round(_value(r, k), 3) for k, _ in METRICS))


if __name__ == "__main__":
    main()
