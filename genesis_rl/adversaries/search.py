"""Black-box search adversaries: CMA-ES and our cross-entropy method over piecewise-constant knob schedules,
``search_budget`` episodes per scene, reporting the worst episode found (as ARCH-COMP's falsifiers do;
VerifAI's own samplers play through ``adversaries.verifai_search``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from genesis_rl.adversaries.base import (
    EpisodeOutcome,
    EpisodeRunner,
    PolicyContext,
    SearchLedger,
    WeatherPolicy,
    chooses_start,
    register_policy,
)
from genesis_rl.core.errors import UserInputError


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
        from genesis_rl.core import limits

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
        ledger = SearchLedger()
        for _ in range(self.budget // popsize):
            xs = es.ask()
            fitness = [-ledger.add(self._play(runner, np.asarray(x), scene, episode_seed, k)) for x in xs]
            es.tell(xs, fitness)
        return ledger.report(popsize=popsize)

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
    """Our own cross-entropy method (not VerifAI's code: its samplers play as ``verifai_ce`` and the others)
    over the same piecewise-constant schedules as ``cmaes``: a Gaussian per schedule entry, sampled (clipped to
    [-1, 1]) a generation at a time; the best quarter of each generation, at least 2 (by the episode's total
    reward), gives the next mean and spread. It spends exactly ``search_budget`` episodes per scene (the last
    generation takes what is left) and reports its best.
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
        ledger = SearchLedger()
        for n in sizes:
            xs = np.clip(mean + sigma * rng.standard_normal((n, dim)), -1.0, 1.0)
            returns = [ledger.add(self._play(runner, x, scene, episode_seed, k)) for x in xs]
            # at least 2 elites: one has no spread, and the search would collapse to MIN_SIGMA at once
            elite = xs[np.argsort(returns)[::-1][: max(2, int(np.ceil(self.ELITE_FRACTION * n)))]]
            mean, sigma = elite.mean(axis=0), np.maximum(elite.std(axis=0), self.MIN_SIGMA)
        return ledger.report(generations=sizes)


class BudgetedSearch(WeatherPolicy):
    """A search that plays whole episodes, ``search_budget`` of them a scene (at least 1), and reports its best."""

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        self.budget = int(context.options.get("search_budget", 8))
        if self.budget < 1:
            raise UserInputError(f"search_budget = {self.budget} must be >= 1")
        from genesis_rl.core import limits

        limits.SEARCH_BUDGET.check(self.budget, "search_budget")

    @classmethod
    def episodes_per_scene(cls, options: dict[str, Any]) -> int:
        return int(options.get("search_budget", 8))


@register_policy
class RandomSearch(BudgetedSearch):
    """Random testing at a search's budget: ``search_budget`` episodes of uniform random actions per scene, each
    with its own draws (and, when the campaign lets policies choose the start, its own start drawn inside the
    ODD, as ``random``'s), reporting the best by total reward. ``random`` plays one episode a scene; this is the
    baseline a search must beat at equal simulator budget, as fuzzers are measured against random testing."""

    name = "random_search"
    description = "random at a search's budget: search_budget random episodes per scene, the best reported"

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        choose = chooses_start(self.context.options) and bool(runner.held_knobs)
        ledger = SearchLedger()
        for i in range(self.budget):
            rng = np.random.default_rng([self.context.seed, scene, episode_seed, 6, i])
            start = runner.natural_start(rng) if choose else None

            def act(obs: Any, rng: np.random.Generator = rng) -> np.ndarray:
                return rng.uniform(-1.0, 1.0, self.context.action_dim).astype(np.float32)

            ledger.add(runner.run(act, scene, episode_seed, start))
        return ledger.report()


@register_policy
class CornerSearch(BudgetedSearch):
    """The corners of the action box at a search's budget: each candidate pushes every knob to one end and holds
    it there (a constant action of +-1 per knob; a held knob, such as the sun under natural dynamics, starts at
    that end when the campaign lets policies choose the start), and the best episode (by total reward) is
    reported. With 2^K corners over K knobs and a smaller ``search_budget``, the corners played are drawn
    without replacement from the scene's seeds. ``constant`` is one fixed corner (+1 on every knob, the sun at
    noon); this is the best corner a scene offers, and under the benchmark's transfer protocol the best corner
    of the tuning scenes, replayed on held-out ones: the open-loop reference a reactive adversary must beat."""

    name = "corner_search"
    description = "the best corner of the action box (each knob held at one end), search_budget corners per scene"

    def corners(self, scene: int, episode_seed: int) -> list[int]:
        """The corners this scene plays, as bit masks (bit i set: knob i at +1), in increasing order."""
        count = 2 ** self.context.action_dim
        if self.budget >= count:
            return list(range(count))
        rng = np.random.default_rng([self.context.seed, scene, episode_seed, 7])
        return sorted(int(c) for c in rng.choice(count, size=self.budget, replace=False))

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        choose = chooses_start(self.context.options) and bool(runner.held_knobs)
        ledger = SearchLedger()
        picked = self.corners(scene, episode_seed)
        for mask in picked:
            action = np.array([1.0 if mask >> i & 1 else -1.0 for i in range(self.context.action_dim)], np.float32)
            start = runner.start_from([(float(action[i]) + 1.0) / 2.0 for i in runner.held_indices()]) \
                if choose else None

            def act(obs: Any, a: np.ndarray = action) -> np.ndarray:
                return a

            ledger.add(runner.run(act, scene, episode_seed, start))
        return ledger.report(corners=picked)
