"""What every adversary is: a policy that plays one episode on a scene through an ``EpisodeRunner``, and the
registry that finds it by name.

Step policies (``sunny``, ``random``, ``constant``, ``agent``) choose an action in [-1, 1]^K from each observation,
under the same naturalness limit as the trained agent. Search policies (``cmaes``, ``cem``, ``mcts``) spend several
episodes of simulator budget on each scene and keep the worst one they find, which is what a black-box falsifier
would report; their ``sim_steps`` count every episode they spent. Campaigns (``evaluation/``) and the benchmark
(``benchmark/``) know adversaries only through this module's interface.

Register your own with ``@register_policy`` or name it by import path (``package.module:Class``)::

    @register_policy
    class AlwaysFoggier(StepPolicy):
        name = "foggier"
        def act(self, obs):
            return np.ones(self.context.action_dim, np.float32)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.plugins import load_class
from genesis_rl.sim.interface import ActorEvent
from genesis_rl.world.knobs import Weather
from genesis_rl.world.odd.domain import IN_ODD
from genesis_rl.world.step_record import StepRecord

POLICIES: dict[str, type[WeatherPolicy]] = {}


def register_policy(cls: type[WeatherPolicy]) -> type[WeatherPolicy]:
    POLICIES[cls.name] = cls
    return cls


@dataclass
class EpisodeOutcome:
    """What a policy's episode left: the step records, frames around the first collision (step -> RGB),
    the simulator steps spent (a search counts all its candidates) and policy-specific extras."""

    records: list[StepRecord]
    frames: dict[int, np.ndarray] = field(default_factory=dict)
    sim_steps: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    #: what the actor knobs made happen (cut-ins, a lead braking), for the careful-driver reference
    actor_events: list[ActorEvent] = field(default_factory=list)
    #: the weather the episode started from (None: the env's start weather)
    start: Weather | None = None
    #: the knob trajectory's log-likelihood ratio against held weather [nats, <= 0] (``WeatherModel.naturalness``;
    #: None: the runner did not compute it)
    naturalness: float | None = None

    @property
    def total_reward(self) -> float:
        return float(sum(r.reward["reward"] for r in self.records))


def in_odd_failure_at(records: Sequence[StepRecord]) -> int | None:
    """The index of the first step at which a collision began inside the ODD (or on its boundary); None: none."""
    for i, rec in enumerate(records):
        began = rec.collision.collided and (i == 0 or not records[i - 1].collision.collided)
        if began and rec.odd_status in IN_ODD:
            return i
    return None


@dataclass
class SearchLedger:
    """A search's books, candidate by candidate: the best episode so far, the simulator steps spent, each
    candidate's return, and each candidate's steps and the index of its in-ODD failure (None: none), so that a
    benchmark can count the simulator steps to the first in-ODD failure (ARCH-COMP's simulations to the first
    falsification) and not only those of the episode the search reports."""

    steps: list[int] = field(default_factory=list)
    failures: list[int | None] = field(default_factory=list)
    returns: list[float] = field(default_factory=list)
    spent: int = 0
    best: EpisodeOutcome | None = None
    best_value: float = -math.inf

    def add(self, outcome: EpisodeOutcome, value: float | None = None) -> float:
        """Book one candidate, kept as the best when its value (default: its total reward) beats the best's;
        returns that value."""
        reward = outcome.total_reward
        v = reward if value is None else value
        self.steps.append(len(outcome.records))
        self.failures.append(in_odd_failure_at(outcome.records))
        self.returns.append(round(reward, 3))
        self.spent += outcome.sim_steps
        if self.best is None or v > self.best_value:
            self.best, self.best_value = outcome, v
        return v

    def report(self, **extra: Any) -> EpisodeOutcome:
        """The best episode, charged with every step the search spent, its extras the search's books."""
        assert self.best is not None, "a search books at least one candidate"
        self.best.sim_steps = self.spent
        self.best.extra = {"search_returns": list(self.returns), **extra, "candidate_steps": list(self.steps),
                           "candidate_failures": list(self.failures)}
        return self.best


class EpisodeRunner(Protocol):
    def run(self, act: Callable[[Any], np.ndarray], scene: int, episode_seed: int,
            start: Weather | None = None, start_head: bool = False) -> EpisodeOutcome:
        """One episode; ``start_head``: ``act``'s first action chooses the start (``GenesisEnv.chosen_start``)."""
        ...

    def play_schedule(self, scene: int, episode_seed: int, start: Weather | None,
                      schedule: Sequence[Weather]) -> EpisodeOutcome:
        """One episode whose weather follows ``schedule`` open loop from ``start`` (``adversaries.replay``)."""
        ...

    @property
    def has_start_head(self) -> bool:
        """Whether the env observes the start step (``env.start_head``), so an agent may choose its start."""
        ...

    @property
    def held_knobs(self) -> tuple[str, ...]: ...

    @property
    def knobs(self) -> tuple[str, ...]:
        """The knobs the action vector turns, in its order."""
        ...

    @property
    def last_record(self) -> StepRecord | None:
        """The latest step's record (None before the first): what a tester watching the drive sees."""
        ...

    def held_indices(self) -> list[int]: ...

    def start_from(self, position: Sequence[float]) -> Weather: ...

    def natural_start(self, rng: np.random.Generator) -> Weather: ...


class ExploringRunner(EpisodeRunner, Protocol):
    """A runner that an explorer drives step by step and returns to saved states (``GenesisEnv.snapshot``):
    lite can, CARLA refuses with a message that says why."""

    def begin(self, scene: int, episode_seed: int, start: Weather | None = None) -> None:
        """Start an episode as ``run`` would (same seeds, same world), without playing it."""
        ...

    def step(self, action: np.ndarray) -> StepRecord:
        """One step of the episode under ``action``; its record."""
        ...

    @property
    def steps_taken(self) -> int:
        """Steps of the current episode so far."""
        ...

    @property
    def heading_deg(self) -> float:
        """The ego camera's heading now [deg, counter-clockwise from east]."""
        ...

    def snapshot(self) -> object: ...

    def restore(self, snapshot: object) -> None: ...


#: campaign option ``start``: "fixed" (every episode from the env's start weather, as before) or "natural"
#: (each policy chooses where the knobs that cannot move within an episode start: the sun's position under
#: natural dynamics; random draws it, constant takes its corner, the searches search it, an agent trained with
#: a start head (``env.start_head``) chooses it with its first action, sunny and other agents keep the start
#: weather)
STARTS = ("fixed", "natural")


def chooses_start(options: dict[str, Any]) -> bool:
    """Whether the campaign's policies choose their start (option ``start``); a bad value is refused."""
    value = options.get("start", "fixed")
    if value not in STARTS:
        raise UserInputError(f"campaign option start = {value!r}; allowed: {', '.join(STARTS)}")
    return value == "natural"


@dataclass(frozen=True)
class PolicyContext:
    """What a policy is built from: the action size, the campaign seed, the trained agent (if any) and
    policy options (``--search-budget`` and the like)."""

    action_dim: int
    seed: int
    agent_path: Path | None = None
    options: dict[str, Any] = field(default_factory=dict)


class WeatherPolicy:
    name: ClassVar[str] = ""
    needs_agent: ClassVar[bool] = False
    #: whether the policy acts on what it observes (a trained agent, a scripted watcher): a benchmark re-runs
    #: its failures by playing it again in a fresh world; a policy that does not react is judged by the
    #: schedule it played, replayed there
    reacts: ClassVar[bool] = False
    description: ClassVar[str] = ""

    def __init__(self, context: PolicyContext) -> None:
        self.context = context

    @classmethod
    def episodes_per_scene(cls, options: dict[str, Any]) -> int:
        """Simulator episodes one scene costs (a search spends its budget): campaigns start the longest first."""
        return 1

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        raise NotImplementedError


class StepPolicy(WeatherPolicy):
    """A policy that acts step by step; ``reset`` is called before each episode."""

    def reset(self, scene: int, episode_seed: int) -> None:
        pass

    def act(self, obs: Any) -> np.ndarray:
        raise NotImplementedError

    def start(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> Weather | None:
        """Where the episode starts when the campaign lets policies choose (``chooses_start``); None: the
        env's start weather (the default, and always for policies that do not choose)."""
        return None

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        self.reset(scene, episode_seed)
        start = self.start(runner, scene, episode_seed) if chooses_start(self.context.options) else None
        return runner.run(self.act, scene, episode_seed, start)


def resolve_policy(name: str) -> type[WeatherPolicy]:
    """A registered policy name, or ``package.module:Class`` of a WeatherPolicy subclass."""
    if name in POLICIES:
        return POLICIES[name]
    if ":" in name:
        return load_class(name, "policy", {}, base=WeatherPolicy)
    raise UserInputError(f"unknown policy '{name}'; allowed: {', '.join(POLICIES)} or package.module:Class")
