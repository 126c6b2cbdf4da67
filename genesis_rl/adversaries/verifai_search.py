"""VerifAI's own samplers as adversaries (the ``verifai`` extra, ``verifai==2.2.0`` from PyPI): the peer itself
in the benchmark, not a re-implementation of it.

Each plays the same piecewise-constant schedules (and, where the campaign lets policies choose it, the same
start) as ``cmaes``, through VerifAI's API: a ``FeatureSpace`` with one ``Box`` feature over the candidate's
entries in [-1, 1], a sampler made by ``FeatureSampler.<kind>SamplerFor``, and ``getSample`` / ``update`` with
each episode's robustness ``rho`` as VerifAI's monitors define it (lower is closer to failure):

- an in-ODD collision: ``-1``;
- otherwise the smallest true bumper gap to the lead over the episode [m] (:data:`NO_LEAD_RHO` when it never
  had one).

Samples whose ``rho`` is below ``verifai_threshold`` (option, default :data:`NEAR_MISS_M`: a near miss) are the
counterexamples the cross-entropy and bandit samplers learn from; Bayesian optimisation minimises ``rho``. Each
sample costs one episode, ``search_budget`` a scene, and the search reports its episode of lowest ``rho``.
VerifAI draws from Python's and numpy's global generators: they are seeded for each scene from the campaign
seed, the scene and the episode seed, and put back as they were afterwards, so an episode replays exactly.
"""

from __future__ import annotations

import math
import random
from typing import Any, ClassVar

import numpy as np

from genesis_rl.adversaries.base import (
    EpisodeOutcome,
    EpisodeRunner,
    PolicyContext,
    SearchLedger,
    in_odd_failure_at,
    register_policy,
)
from genesis_rl.adversaries.search import CMAESSearch
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.step_record import StepRecord

#: the default counterexample threshold on ``rho`` [m]: an episode that came this close to the lead
NEAR_MISS_M = 5.0
#: ``rho`` of an episode that never had a lead ahead [m] (past lite's 80 m lead range)
NO_LEAD_RHO = 100.0


def robustness(records: list[StepRecord]) -> float:
    """The episode's ``rho`` (module docstring)."""
    if in_odd_failure_at(records) is not None:
        return -1.0
    gaps = [r.lead.true_distance for r in records if math.isfinite(r.lead.true_distance)]
    return float(min(gaps)) if gaps else NO_LEAD_RHO


def _verifai() -> Any:
    try:
        import verifai.features as features
        import verifai.samplers as samplers
    except ImportError as err:
        raise UserInputError("the verifai_* adversaries need VerifAI: pip install 'genesis-rl[verifai]' "
                             f"(verifai 2.2.0; here: {err})") from None
    return features, samplers


class VerifaiSearch(CMAESSearch):
    """One of VerifAI's samplers over ``cmaes``'s candidate schedules (module docstring)."""

    #: the ``FeatureSampler`` factory's kind: ce, mab, bo
    kind: ClassVar[str] = ""
    factories: ClassVar[dict[str, str]] = {"ce": "crossEntropySamplerFor", "mab": "multiArmedBanditSamplerFor",
                                           "bo": "bayesianOptimizationSamplerFor"}

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        self.threshold = float(context.options.get("verifai_threshold", NEAR_MISS_M))
        if not math.isfinite(self.threshold):
            raise UserInputError(f"verifai_threshold = {self.threshold!r}; allowed: a finite number of metres")

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        features, samplers = _verifai()
        k = self._start_dims(runner)
        dim = self.segments * self.context.action_dim + k
        seed = int(np.random.default_rng([self.context.seed, scene, episode_seed, 7]).integers(1, 2**31 - 1))
        # VerifAI draws from the legacy global generators: seed them for this scene, put them back afterwards
        saved = random.getstate(), np.random.get_state()  # noqa: NPY002
        random.seed(seed)
        np.random.seed(seed)  # noqa: NPY002
        try:
            space = features.FeatureSpace({"schedule": features.Feature(features.Box(*[(-1.0, 1.0)] * dim))})
            params = samplers.feature_sampler.default_sampler_params(self.kind)
            if self.kind in ("ce", "mab"):
                params.thres = self.threshold
            else:
                params.init_num = max(1, min(5, self.budget // 2))
            sampler = getattr(samplers.FeatureSampler, self.factories[self.kind])(space, params)
            ledger = SearchLedger()
            rhos = []
            for _ in range(self.budget):
                point, info = sampler.getSample()
                x = np.clip(np.asarray(point.schedule, np.float64), -1.0, 1.0)
                outcome = self._play(runner, x, scene, episode_seed, k)
                rho = robustness(outcome.records)
                rhos.append(round(rho, 3))
                ledger.add(outcome, value=-rho)  # the lowest rho is the episode it reports
                sampler.update(point, info, rho)
        finally:
            random.setstate(saved[0])
            np.random.set_state(saved[1])  # noqa: NPY002
        return ledger.report(verifai_sampler=self.kind, rho=rhos)


@register_policy
class VerifaiCrossEntropy(VerifaiSearch):
    name = "verifai_ce"
    kind = "ce"
    description = "VerifAI's cross-entropy sampler (verifai 2.2.0) over cmaes' schedules, search_budget episodes"


@register_policy
class VerifaiBandit(VerifaiSearch):
    name = "verifai_mab"
    kind = "mab"
    description = "VerifAI's multi-armed bandit sampler (verifai 2.2.0) over cmaes' schedules, search_budget episodes"


@register_policy
class VerifaiBayesOpt(VerifaiSearch):
    name = "verifai_bo"
    kind = "bo"
    description = "VerifAI's Bayesian optimisation sampler (verifai 2.2.0, GPyOpt) over cmaes' schedules"

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        try:  # refused before any episode runs, not when the matrix reaches it
            import GPyOpt  # noqa: F401
        except ImportError as err:
            raise UserInputError("verifai_bo needs GPyOpt, which VerifAI's Bayesian optimisation sampler calls: pip "
                                 f"install 'genesis-rl[verifai]' (here: {err})") from None
