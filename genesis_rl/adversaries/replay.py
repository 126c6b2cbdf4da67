"""A schedule tuned elsewhere, played open loop: how a search takes part in a transfer test.

A search adapts to the scene it is given by spending episodes on it. Under the benchmark's transfer protocol
it may not: it searches the tuning scenes, and on each held-out scene it plays the best schedule it found
there once, start included (``benchmark.transfer``). A ``Schedule`` is that schedule as absolute knob values
(the weather it starts from and every step's knobs, actor knobs included), so it needs no model of the search
that made it; ``ScheduleReplay`` plays it under the search's own name, through
``EpisodeRunner.play_schedule``. It does not react: a benchmark's re-runs replay what it played.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from genesis_rl.adversaries.base import EpisodeOutcome, EpisodeRunner, PolicyContext, WeatherPolicy
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.knobs import KNOBS, Weather

#: the campaign option that names, per policy, the schedule it replays instead of playing itself
OPTION = "schedules"


@dataclass(frozen=True)
class Schedule:
    """An open-loop schedule: the start (None: the env's start weather) and every step's knob values."""

    start: Weather | None
    steps: tuple[Weather, ...]

    def to_json(self) -> dict[str, Any]:
        """Compact JSON: the start's values, and per knob its values over the steps (floats round-trip)."""
        return {"start": None if self.start is None else dict(self.start.values),
                "steps": {k: [float(w.values[k]) for w in self.steps] for k in KNOBS}}

    @classmethod
    def from_json(cls, data: Any, where: str) -> Schedule:
        """The schedule ``to_json`` wrote; anything else is refused naming ``where`` and the field."""
        if not isinstance(data, Mapping) or set(data) != {"start", "steps"}:
            raise UserInputError(f"{where}: a schedule is an object with fields start and steps")
        start = data["start"]
        if start is not None and not isinstance(start, Mapping):
            raise UserInputError(f"{where}.start: an object of knob values, or null")
        steps = data["steps"]
        if not isinstance(steps, Mapping) or set(steps) != set(KNOBS):
            raise UserInputError(f"{where}.steps: an object with one list per knob ({', '.join(KNOBS)})")
        lengths = {len(v) if isinstance(v, list) else -1 for v in steps.values()}
        if len(lengths) != 1 or min(lengths) < 1:
            raise UserInputError(f"{where}.steps: one non-empty list per knob, all of one length")
        for knob, values in steps.items():
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
                raise UserInputError(f"{where}.steps.{knob}: finite numbers only")
        count = lengths.pop()
        return cls(None if start is None else Weather.from_recorded(start),
                   tuple(Weather.from_recorded({k: float(steps[k][i]) for k in KNOBS}) for i in range(count)))

    @classmethod
    def of_episode(cls, start: Weather | None, knobs: Sequence[Mapping[str, float]]) -> Schedule:
        """The schedule an episode played: its start and its step records' knobs."""
        return cls(start, tuple(Weather.from_recorded(k) for k in knobs))


class ScheduleReplay(WeatherPolicy):
    """Plays one fixed schedule on every scene (not registered: a campaign builds it for a policy that its
    option ``schedules`` names, and it plays under that policy's name)."""

    name = "schedule_replay"
    description = "a schedule tuned on other scenes, played open loop"

    def __init__(self, context: PolicyContext, schedule: Schedule) -> None:
        super().__init__(context)
        self.schedule = schedule

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        return runner.play_schedule(scene, episode_seed, self.schedule.start, self.schedule.steps)


def schedules_option(options: Mapping[str, Any]) -> Mapping[str, Any]:
    """A campaign's option ``schedules`` (empty when absent): policy -> schedule, or refused naming it."""
    given = options.get(OPTION)
    if given is None:
        return {}
    if not isinstance(given, Mapping):
        raise UserInputError(f"campaign option {OPTION}: an object of policy -> schedule")
    return given


def replayed_schedule(options: Mapping[str, Any], policy: str) -> Schedule | None:
    """The schedule a campaign's option ``schedules`` gives ``policy`` (None: the policy plays itself)."""
    given = schedules_option(options)
    if policy not in given:
        return None
    return Schedule.from_json(given[policy], f"campaign option {OPTION}.{policy}")


def build_policy(cls: type[WeatherPolicy], name: str, context: PolicyContext) -> WeatherPolicy:
    """The policy a campaign plays as ``name``: its class, or the schedule its options give it to replay."""
    schedule = replayed_schedule(context.options, name)
    return cls(context) if schedule is None else ScheduleReplay(context, schedule)
