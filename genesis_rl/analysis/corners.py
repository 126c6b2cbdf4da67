"""The best constant schedule: every corner of the action box, played on training scenes.

A constant action pushes each knob the same way every step (``constant`` policy), so each knob runs to a
bound (of its range, or of the ODD, which projects the weather back inside) and stays there: the schedule
ends in a corner of the domain. There are 2^m corners over the m knobs that can move. A knob the dynamics
hold (the sun in the natural preset moves 0.1 deg in an episode) or a disabled one gets action 0. This plays
every corner on the same training scenes and episode seeds and ranks them by the mean episode return (the
agent's objective), then collisions. The winner is the open-loop reference a reactive agent must beat on the
test map; it is chosen on the training map, as the agent is trained there.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from genesis_rl.analysis.reactivity import METRICS, play_closed

#: a knob that cannot move this share of its range in an episode is held (the sun in the natural preset: 0.1 deg)
MIN_TRAVEL = 0.01


def movable(env: Any) -> list[int]:
    """Indices of the action's knobs that can move at least MIN_TRAVEL of their range in an episode."""
    from genesis_rl.world.knobs import KNOBS

    steps = env.config.episode_steps
    return [i for i, (k, d) in enumerate(zip(env.config.knobs, env.mapper.max_delta, strict=True))
            if d * steps >= MIN_TRAVEL * KNOBS[k].span]


def corner_actions(env: Any) -> list[np.ndarray]:
    """Every corner: +-1 on each movable knob, 0 on the others; in a fixed order (all -1 first)."""
    idx = movable(env)
    out = []
    for signs in itertools.product((-1.0, 1.0), repeat=len(idx)):
        a = np.zeros(env.mapper.action_dim, np.float32)
        a[idx] = signs
        out.append(a)
    return out


class _Constant:
    def __init__(self, action: np.ndarray) -> None:
        self.action = action

    def reset(self, scene: int, episode_seed: int) -> None:
        pass

    def act(self, obs: Any) -> np.ndarray:
        return self.action


def search_corners(env: Any, scenes: Sequence[int], episode_seeds: Sequence[int],
                   progress: bool = False) -> list[dict[str, Any]]:
    """Each corner's mean return, collisions and per-scene returns on (scene, seed) pairs; best first."""
    corners = corner_actions(env)
    bar = tqdm(total=len(corners) * len(scenes), desc="corners", unit="episode", disable=not progress)
    rows = []
    for action in corners:
        returns, collided = [], 0
        for scene, seed in zip(scenes, episode_seeds, strict=True):
            score, _ = play_closed(env, _Constant(action), int(scene), int(seed), METRICS)
            returns.append(score.metric("reward"))
            collided += int(score.metric("collided"))
            bar.update()
        rows.append({"action": [float(v) for v in action], "mean_return": float(np.mean(returns)),
                     "collisions": collided, "returns": [round(r, 3) for r in returns]})
    bar.close()
    return sorted(rows, key=lambda r: (-r["mean_return"], -r["collisions"], r["action"]))
