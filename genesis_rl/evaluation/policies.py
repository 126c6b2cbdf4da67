"""Weather policies a campaign compares: who turns the knobs while the system under test drives.

A policy plays one episode on a scene through an ``EpisodeRunner`` (see ``campaign``). Step policies
(``sunny``, ``random``, ``agent``) choose an action in [-1, 1]^K from each observation, under the same
naturalness limit as the trained agent. Search baselines (``cmaes``) spend several episodes of simulator
budget on each scene and keep the worst weather schedule they find, which is what a black-box falsifier
would report; their ``sim_steps`` count every episode they spent.

Register your own with ``@register_policy`` or name it by import path (``package.module:Class``)::

    @register_policy
    class AlwaysFoggier(StepPolicy):
        name = "foggier"
        def act(self, obs):
            return np.ones(self.context.action_dim, np.float32)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from genesis_rl.errors import UserInputError
from genesis_rl.knobs import Weather
from genesis_rl.plugins import load_class
from genesis_rl.sim.interface import ActorEvent
from genesis_rl.step_record import StepRecord

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

    @property
    def total_reward(self) -> float:
        return float(sum(r.reward["reward"] for r in self.records))


class EpisodeRunner(Protocol):
    def run(self, act: Callable[[Any], np.ndarray], scene: int, episode_seed: int,
            start: Weather | None = None) -> EpisodeOutcome: ...

    @property
    def held_knobs(self) -> tuple[str, ...]: ...

    def held_indices(self) -> list[int]: ...

    def start_from(self, position: Sequence[float]) -> Weather: ...

    def natural_start(self, rng: np.random.Generator) -> Weather: ...


#: campaign option ``start``: "fixed" (every episode from the env's start weather, as before) or "natural"
#: (each policy chooses where the knobs that cannot move within an episode start: the sun's position under
#: natural dynamics; random draws it, constant takes its corner, the searches search it, sunny and the agent
#: keep the start weather)
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
    schedule that gives the paper agent's figures (docs/results.md): the reference a reactive agent must beat."""

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


@register_policy
class AgentPolicy(StepPolicy):
    name = "agent"
    needs_agent = True
    description = "the trained policy (PPO or SAC), deterministic"

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        self.model = load_agent(context.agent_path)

    def act(self, obs: Any) -> np.ndarray:
        action, _ = self.model.predict(obs, deterministic=True)
        return np.asarray(action, np.float32)


def _agent_candidates(path: Path) -> list[Path]:
    return [path] if path.suffix == ".zip" else [path / "agent.zip", path / "checkpoints" / "last.zip"]


def agent_file(path: Path) -> Path | None:
    """The agent's .zip behind ``--agent``: the file itself, a run folder's agent.zip, else its last
    checkpoint; None when there is none."""
    return next((p for p in _agent_candidates(Path(path)) if p.is_file()), None)


def _run_config(agent: Path) -> Any:
    """The checked config of the run an agent file belongs to (its folder, or the folder above
    checkpoints/); None for a loose file."""
    from genesis_rl.training.config import load_run_config

    for folder in (agent.parent, agent.parent.parent):
        if (folder / "config.toml").is_file():
            try:
                return load_run_config(folder / "config.toml")
            except UserInputError as err:
                raise UserInputError(f"--agent: the run's config '{folder / 'config.toml'}': {err}") from None
    return None


def load_agent(path: Path | None) -> Any:
    """A trained agent (PPO or SAC) from a run folder (its ``agent.zip``, else its last checkpoint) or a .zip
    file, rebuilt from its run's config.toml and the file's tensors: nothing in the file is unpickled
    (training/safe_load.py); a loose file without its run's config loads only with ``--trust-pickle``."""
    from genesis_rl.training.safe_load import load_model

    if path is None:
        raise UserInputError("policy 'agent' needs a trained agent: pass --agent runs/NAME")
    path = Path(path)
    found = agent_file(path)
    if found is None:
        candidates = _agent_candidates(path)
        raise UserInputError(f"--agent '{path}' holds no trained agent (looked for "
                             f"{', '.join(str(c) for c in candidates)}); train one with genesis-rl train")
    return load_model(found, _run_config(found), device="cpu", what="--agent")


@register_policy
class CMAESSearch(WeatherPolicy):
    """Black-box falsification by CMA-ES (the ``cma`` package) over piecewise-constant knob schedules.

    The episode is split into ``search_segments`` equal segments; in each, every knob is pushed by a
    constant action in [-1, 1] (so the same 5% limit holds). Each candidate schedule costs one episode;
    the search spends ``search_budget`` episodes per scene, maximises the episode's total reward (the
    agent's own objective) and reports its best episode.
    """

    name = "cmaes"
    description = "CMA-ES search over piecewise-constant knob schedules, search_budget episodes per scene"

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        opts = context.options
        self.budget = int(opts.get("search_budget", 8))
        self.segments = int(opts.get("search_segments", 4))
        self.sigma0 = float(opts.get("search_sigma", 0.5))
        if self.budget < 2 or self.segments < 1:
            raise UserInputError(f"search_budget = {self.budget} must be >= 2 and search_segments = "
                                 f"{self.segments} >= 1")
        from genesis_rl import limits

        limits.SEARCH_BUDGET.check(self.budget, "search_budget")  # also when a campaign.json sets it

    @classmethod
    def episodes_per_scene(cls, options: dict[str, Any]) -> int:
        return int(options.get("search_budget", 8))

    def _start_dims(self, runner: EpisodeRunner) -> int:
        """How many entries of a candidate choose the start: one per held knob when the campaign lets
        policies choose it (``chooses_start``), else none."""
        return len(runner.held_knobs) if chooses_start(self.context.options) else 0

    def _play(self, runner: EpisodeRunner, x: np.ndarray, scene: int, episode_seed: int, k: int) -> EpisodeOutcome:
        """One candidate's episode: its last ``k`` entries (in [-1, 1]) place the held knobs' start."""
        start = runner.start_from([(float(v) + 1.0) / 2.0 for v in x[len(x) - k:]]) if k else None
        return runner.run(self._schedule(np.asarray(x[:len(x) - k])), scene, episode_seed, start)

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        import cma

        k = self._start_dims(runner)
        dim = self.segments * self.context.action_dim + k
        default_pop = 4 + int(3 * np.log(dim))
        popsize = max(2, min(default_pop, self.budget // 2))
        seed = int(np.random.default_rng([self.context.seed, scene, episode_seed, 2]).integers(1, 2**31 - 1))
        es = cma.CMAEvolutionStrategy(np.zeros(dim), self.sigma0,
                                      {"seed": seed, "popsize": popsize, "bounds": [-1.0, 1.0], "verbose": -9})
        best: EpisodeOutcome | None = None
        spent, history = 0, []
        for _ in range(self.budget // popsize):
            xs = es.ask()
            fitness = []
            for x in xs:
                outcome = self._play(runner, np.asarray(x), scene, episode_seed, k)
                spent += outcome.sim_steps
                fitness.append(-outcome.total_reward)
                history.append(round(outcome.total_reward, 3))
                if best is None or outcome.total_reward > best.total_reward:
                    best = outcome
            es.tell(xs, fitness)
        assert best is not None
        best.sim_steps = spent
        best.extra = {"search_returns": history, "popsize": popsize}
        return best

    def _schedule(self, x: np.ndarray) -> Callable[[Any], np.ndarray]:
        table = np.clip(x.reshape(self.segments, self.context.action_dim), -1.0, 1.0).astype(np.float32)
        steps = int(self.context.options.get("steps", 512))
        state = {"t": 0}

        def act(obs: Any) -> np.ndarray:
            seg = min(self.segments - 1, state["t"] * self.segments // max(steps, 1))
            state["t"] += 1
            return table[seg]

        return act


@register_policy
class CrossEntropySearch(CMAESSearch):
    """The cross-entropy method, as VerifAI's cross-entropy sampler, over the same piecewise-constant schedules
    as ``cmaes``: a Gaussian per schedule entry, sampled (clipped to [-1, 1]) a generation at a time; the best
    quarter of each generation, at least 2 (by the episode's total reward), gives the next mean and spread. It spends
    exactly ``search_budget`` episodes per scene (the last generation takes what is left) and reports its best.
    """

    name = "cem"
    description = "cross-entropy search over piecewise-constant knob schedules, search_budget episodes per scene"
    ELITE_FRACTION = 0.25
    MIN_SIGMA = 0.05  # keeps sampling once the elites agree

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        k = self._start_dims(runner)
        dim = self.segments * self.context.action_dim + k
        rng = np.random.default_rng([self.context.seed, scene, episode_seed, 3])
        generation = max(2, min(4 + int(3 * np.log(dim)), self.budget // 2))
        sizes = [generation] * (self.budget // generation)
        sizes[-1] += self.budget - sum(sizes)  # exactly the budget
        mean, sigma = np.zeros(dim), np.full(dim, self.sigma0)
        best: EpisodeOutcome | None = None
        spent, history = 0, []
        for n in sizes:
            xs = np.clip(mean + sigma * rng.standard_normal((n, dim)), -1.0, 1.0)
            returns = []
            for x in xs:
                outcome = self._play(runner, x, scene, episode_seed, k)
                spent += outcome.sim_steps
                returns.append(outcome.total_reward)
                history.append(round(outcome.total_reward, 3))
                if best is None or outcome.total_reward > best.total_reward:
                    best = outcome
            # at least 2 elites: one has no spread, and the search would collapse to MIN_SIGMA at once
            elite = xs[np.argsort(returns)[::-1][: max(2, int(np.ceil(self.ELITE_FRACTION * n)))]]
            mean, sigma = elite.mean(axis=0), np.maximum(elite.std(axis=0), self.MIN_SIGMA)
        assert best is not None
        best.sim_steps = spent
        best.extra = {"search_returns": history, "generations": sizes}
        return best


def resolve_policy(name: str) -> type[WeatherPolicy]:
    """A registered policy name, or ``package.module:Class`` of a WeatherPolicy subclass."""
    if name in POLICIES:
        return POLICIES[name]
    if ":" in name:
        return load_class(name, "policy", {}, base=WeatherPolicy)
    raise UserInputError(f"unknown policy '{name}'; allowed: {', '.join(POLICIES)} or package.module:Class")
