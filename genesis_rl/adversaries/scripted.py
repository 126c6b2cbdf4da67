"""Scripted adversaries written from a reactive member's mechanism: the ground truth of what reacting buys.

``stall_watcher`` watches the system's detections as any tester can (``EpisodeRunner.last_record``) and, the
first time they repeat exactly while the ego is moving (a stalling camera's stutter), makes the lead brake as
hard and as fast as the natural rates allow, and holds it. Every other knob holds. It is what a learned
adversary must at least match on ``stall_braking``; ``fixed_onset`` is the open-loop schedule it is measured
against (the lead brakes from a fixed time, whatever the system does).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from genesis_rl.adversaries.base import EpisodeOutcome, EpisodeRunner, PolicyContext, StepPolicy, register_policy
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.step_record import StepRecord

#: below this ego speed [m/s] repeated detections say nothing (a standing ego sees a standing scene)
MOVING_SPEED = 5.0


def detections_repeat(before: StepRecord | None, now: StepRecord | None) -> bool:
    """Whether ``now``'s detections are ``before``'s exactly (and not empty) while the ego moves."""
    if before is None or now is None or not now.perception.detections:
        return False
    return now.ego.speed > MOVING_SPEED and now.perception.detections == before.perception.detections


def lead_index(runner: EpisodeRunner) -> int | None:
    """Where ``lead_decel`` sits in the action vector; None where the env does not turn it: the scripted
    policies then hold every knob (a benchmark plays every policy on every member; their mechanism is not
    there)."""
    knobs = list(runner.knobs)
    return knobs.index("lead_decel") if "lead_decel" in knobs else None


@register_policy
class StallWatcher(StepPolicy):
    name = "stall_watcher"
    reacts = True
    description = "scripted: brakes the lead hard as soon as the system's detections repeat (stall_braking's truth)"

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        index = lead_index(runner)
        state: dict[str, Any] = {"seen": None, "braking": False}

        def act(obs: Any) -> np.ndarray:
            now = runner.last_record
            if not state["braking"] and detections_repeat(state["seen"], now):
                state["braking"] = True
            state["seen"] = now
            action = np.zeros(self.context.action_dim, np.float32)
            if index is not None:
                action[index] = 1.0 if state["braking"] else 0.0
            return action

        return runner.run(act, scene, episode_seed, None)


@register_policy
class FixedOnset(StepPolicy):
    """The lead brakes as hard and as fast as the natural rates allow from ``--onset-s`` (option ``onset_s``)."""

    name = "fixed_onset"
    description = "open loop: the lead brakes hard from a fixed time (option onset_s), whatever the system does"

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        self.onset_s = float(context.options.get("onset_s", 0.0))
        if not np.isfinite(self.onset_s) or self.onset_s < 0.0:
            raise UserInputError(f"option onset_s = {self.onset_s!r}; allowed: a number of seconds >= 0")

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        index = lead_index(runner)

        def act(obs: Any) -> np.ndarray:
            now = runner.last_record
            t = 0.0 if now is None else now.time_s
            action = np.zeros(self.context.action_dim, np.float32)
            if index is not None:
                action[index] = 1.0 if t >= self.onset_s else 0.0
            return action

        return runner.run(act, scene, episode_seed, None)
