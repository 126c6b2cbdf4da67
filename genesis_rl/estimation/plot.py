"""``estimate.png``: the estimate converging with its interval, beside the starts the episodes were drawn from
(failures marked), so a reader sees both whether to trust the number and where the probability lives."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.core.files.io_utils import atomic_write
from genesis_rl.estimation.nominal import BRAKE_DECEL, BRAKE_ONSET, NominalModel


def plot_estimate(path: Path, rows: Sequence[dict[str, Any]], result: dict[str, Any], nominal: NominalModel) -> None:
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    run = result["running"]
    n = [r["episodes"] for r in run]
    ax.fill_between(n, [r["low"] for r in run], [r["high"] for r in run], color="tab:blue", alpha=0.2,
                    label="95 % interval")
    ax.plot(n, [r["probability"] for r in run], color="tab:blue", label="estimate")
    est = result["estimate"]
    # the estimate's own count: the running curve is sampled every n // 100 episodes, so its last point may
    # fall short of it (a crude estimate of 1,350 was labelled "after 11 pilot episodes")
    pilots = int(result.get("episodes_spent", est["episodes"])) - int(est["episodes"])
    after = f" in the estimate (after {pilots} pilot episode{'s' if pilots > 1 else ''})" if pilots > 0 else ""
    ax.set_xlabel("episodes" + after)
    ax.set_ylabel("failure probability per episode")
    ax.set_title(f"{est['method']}: {est['probability']:.2e} [{est['ci95'][0]:.2e}, {est['ci95'][1]:.2e}]",
                 fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    names = [r.name for r in nominal.starts]
    if nominal.has_braking_event:  # where a braking member's failures live: how hard, and when
        names = [BRAKE_DECEL, BRAKE_ONSET]
    x_name, y_name = (names + [None])[:2] if len(names) >= 1 else (None, None)
    if x_name is not None:
        x = np.array([float(r[f"start_{x_name}"]) for r in rows])
        y = np.array([float(r[f"start_{y_name}"]) for r in rows]) if y_name else np.array([r["index"] for r in rows])
        failed = np.array([bool(r["failed"]) for r in rows])
        stage = np.array([int(r["stage"]) for r in rows])
        last = int(stage.max())
        cmap = plt.colormaps["viridis"].resampled(last + 1)
        sc = bx.scatter(x[~failed], y[~failed], c=stage[~failed], s=8, cmap=cmap, alpha=0.6,
                        vmin=-0.5, vmax=last + 0.5)
        bx.scatter(x[failed], y[failed], marker="x", color="tab:red", s=40, label="in-ODD failure")
        if last > 0:
            bar = fig.colorbar(sc, ax=bx, ticks=range(last + 1))
            bar.set_label(f"stage (0: the broad pilot; {last}: the last)")
        bx.set_xlabel(f"start {x_name}")
        bx.set_ylabel(f"start {y_name}" if y_name else "episode")
        bx.set_title(f"{len(rows)} episodes, {int(failed.sum())} failed", fontsize=10)
        bx.grid(alpha=0.3)
        if failed.any():
            bx.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    atomic_write(path, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)
