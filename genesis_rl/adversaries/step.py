"""Step adversaries that need no search and no training: the start weather held (``sunny``), random actions at
natural rates (``random``) and an open-loop schedule (``constant``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from genesis_rl.adversaries.base import EpisodeRunner, PolicyContext, StepPolicy, register_policy
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.knobs import Weather


@register_policy
class SunnyPolicy(StepPolicy):
    name = "sunny"
    description = "the start weather (clear noon), held constant"

    def act(self, obs: Any) -> np.ndarray:
        return np.zeros(self.context.action_dim, np.float32)


@register_policy
class RandomPolicy(StepPolicy):
    name = "random"
    description = "uniform random actions in [-1, 1] under the same 5% per-step limit"

    def reset(self, scene: int, episode_seed: int) -> None:
        self.rng = np.random.default_rng([self.context.seed, scene, episode_seed, 1])

    def act(self, obs: Any) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, self.context.action_dim).astype(np.float32)

    def start(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> Weather | None:
        """A natural start: the held knobs drawn uniformly inside the ODD (``GenesisEnv.natural_start``)."""
        if not runner.held_knobs:
            return None
        return runner.natural_start(np.random.default_rng([self.context.seed, scene, episode_seed, 4]))


@register_policy
class ConstantPolicy(StepPolicy):
    """The same action every step (``--constant-action``, one value in [-1, 1] per knob; default +1 on every
    knob): an open-loop schedule. +1 on fog, rain and deposits and on the sun's altitude (noon) is the
    schedule that gives the paper agent's figures (docs/results/): the reference a reactive agent must beat."""

    name = "constant"
    description = "the same action every step (--constant-action), an open-loop schedule"

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        raw = context.options.get("constant_action")
        values = [1.0] * context.action_dim if raw is None else [float(v) for v in raw]
        if len(values) == 1:
            values = values * context.action_dim
        if len(values) != context.action_dim or not all(-1.0 <= v <= 1.0 for v in values):
            raise UserInputError(f"--constant-action = {raw!r}: give one value in [-1, 1], or one per knob "
                                 f"({context.action_dim})")
        self.action = np.array(values, np.float32)

    def act(self, obs: Any) -> np.ndarray:
        return self.action

    def start(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> Weather | None:
        """Its corner for the held knobs too: -1 starts a held knob as low as the ODD allows, +1 as high."""
        idx = runner.held_indices()
        if not idx:
            return None
        return runner.start_from([(float(self.action[i]) + 1.0) / 2.0 for i in idx])
