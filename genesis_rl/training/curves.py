"""Learning curves of a training run, from its ``episodes.csv`` (one row per finished episode)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np


def read_episodes(run: Path) -> list[dict[str, float]]:
    path = Path(run) / "episodes.csv"
    if not path.is_file():
        return []
    rows = []
    with path.open() as f:
        reader = csv.DictReader(f)
        try:
            for row in reader:
                try:  # a run killed mid-write may leave a truncated last line
                    rows.append({k: float(v) for k, v in row.items() if k is not None})
                except (TypeError, ValueError):
                    continue
        except csv.Error as err:  # a cell over the csv module's limit: a damaged or foreign file
            from genesis_rl.core.errors import UserInputError
            from genesis_rl.core.parsing import csv_error_reason

            raise UserInputError(f"episode log '{path}' line {reader.reader.line_num}: {csv_error_reason(err)}"
                                 ) from None
    return rows


def plot_learning_curve(run: Path, window: int = 8) -> Any | None:
    """A matplotlib figure: episode reward, rule violations and knob means against training steps, each
    with a running mean over ``window`` episodes; None when the run has no finished episode."""
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    rows = read_episodes(run)
    if not rows:
        return None
    t = np.array([r["timesteps"] for r in rows])
    order = np.argsort(t, kind="stable")
    t = t[order]

    def col(name: str) -> np.ndarray:
        return np.array([rows[i][name] for i in order])

    def smooth(y: np.ndarray) -> np.ndarray:
        k = min(window, len(y))
        return np.convolve(y, np.ones(k) / k, mode="valid")

    panels = [(k, title) for k, title in (("episode_reward", "episode reward"),
                                          ("violation_collision", "collision violation [m/s]"),
                                          ("violation_proximity", "proximity violation [m/s]"),
                                          ("mean_iou", "mean IoU")) if k in rows[0]]
    knobs = [k for k in rows[0] if k.startswith("mean_") and k != "mean_iou"]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(4.0 * (len(panels) + 1), 3.2))
    for ax, (name, title) in zip(axes, panels, strict=False):
        y = col(name)
        ax.plot(t, y, ".", ms=3, color="#95a5a6")
        if len(y) >= 2:
            ax.plot(t[len(t) - len(smooth(y)):], smooth(y), color="#c0392b", lw=1.8)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("training steps")
        ax.grid(alpha=0.3)
    from genesis_rl.world.knobs import KNOBS

    ax = axes[-1]
    for name in knobs:
        knob = name[len("mean_"):]
        if knob in KNOBS:
            spec = KNOBS[knob]
            y = (col(name) - spec.low) / spec.span
            ax.plot(t[len(t) - len(smooth(y)):], smooth(y), lw=1.5, label=knob.replace("_angle", ""))
    ax.set_title("knob means (fraction of range)", fontsize=10)
    ax.set_xlabel("training steps")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.suptitle(f"Training: {Path(run).name} ({len(rows)} episodes; line: running mean of {window})", fontsize=11)
    fig.tight_layout()
    return fig
