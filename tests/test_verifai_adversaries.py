# ruff: noqa: NPY002 - VerifAI draws from numpy's legacy global generator: the tests seed and read that one
"""VerifAI's own samplers as adversaries: through verifai 2.2.0's API, at the search budget, reproducible to the
seed, and leaving Python's and numpy's global generators as they found them."""

from __future__ import annotations

import random

import numpy as np
import pytest

from genesis_rl.adversaries.base import EpisodeOutcome, PolicyContext, resolve_policy
from genesis_rl.adversaries.verifai_search import NO_LEAD_RHO, robustness
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.step_record import CollisionStep, EgoStep, LeadStep, PerceptionStep, StepRecord

pytest.importorskip("verifai")


def _record(i: int, gap: float) -> StepRecord:
    hit = gap <= 0.0
    return StepRecord(step=i + 1, time_s=0.05 * (i + 1), ego=EgoStep(20.0, 0.0, 0.0, 0.0, "follow"),
                      lead=LeadStep(3, max(gap, 0.0), 20.0, gap, True), perception=PerceptionStep(0, 1, 0.0, (), ()),
                      collision=CollisionStep(hit, 20.0 if hit else 0.0, 3 if hit else -1), knobs={},
                      reward={"reward": 0.0}, odd_status="inside")


class _Runner:
    """An episode whose lead gap closes with the schedule's first knob: 30 m less 40 m times its mean action
    (a collision below 0), so that a sampler that learns pushes that knob up."""

    held_knobs: tuple[str, ...] = ()
    knobs = ("fog_density", "lead_decel")

    def __init__(self) -> None:
        self.episodes = 0

    def run(self, act, scene, episode_seed, start=None, start_head=False):  # noqa: ANN001, ANN201
        self.episodes += 1
        actions = [act(None) for _ in range(8)]
        gap = 30.0 - 40.0 * float(np.mean([a[0] for a in actions]))
        return EpisodeOutcome([_record(i, gap if i == 7 else 30.0) for i in range(8)], sim_steps=8)


def _search(name: str, **options):  # noqa: ANN003, ANN202
    return resolve_policy(name)(PolicyContext(2, 5, options={"search_budget": 12, "steps": 8, **options}))


def test_robustness_is_minus_one_for_an_in_odd_collision_else_the_smallest_gap():
    assert robustness([_record(0, 12.0), _record(1, 4.5)]) == 4.5
    assert robustness([_record(0, 12.0), _record(1, -1.0)]) == -1.0
    none = [StepRecord(1, 0.05, EgoStep(20.0, 0, 0, 0, "cruise"), LeadStep(-1, float("nan"), float("nan"),
                                                                                float("nan"), None),
                       PerceptionStep(0, 0, 0.0, (), ()), CollisionStep(False, 0.0, -1), {})]
    assert robustness(none) == NO_LEAD_RHO


@pytest.mark.parametrize("name", ["verifai_ce", "verifai_mab"])
def test_a_verifai_sampler_spends_the_budget_reports_its_lowest_rho_and_replays(name):
    random.seed(123)
    np.random.seed(123)
    before = random.random(), np.random.random()
    random.seed(123)
    np.random.seed(123)
    runner = _Runner()
    outcome = _search(name).run_episode(runner, scene=3, episode_seed=9)
    assert runner.episodes == 12 and outcome.sim_steps == 12 * 8  # every sample an episode, each counted
    rho = outcome.extra["rho"]
    assert len(rho) == 12 and outcome.extra["verifai_sampler"] == name.split("_")[1]
    assert robustness(outcome.records) == pytest.approx(min(rho), abs=1e-3)  # it reports its most falsifying
    assert (random.random(), np.random.random()) == before  # the global generators as they were
    again = _search(name).run_episode(_Runner(), scene=3, episode_seed=9)
    assert again.extra["rho"] == rho  # seeded from the campaign seed, the scene and the episode seed
    other = _search(name).run_episode(_Runner(), scene=4, episode_seed=9)
    assert other.extra["rho"] != rho


def test_the_cross_entropy_sampler_learns_from_its_counterexamples():
    """With near misses (rho < 5 m) as counterexamples, its later samples fail more than its first ones."""
    rho = _search("verifai_ce", search_budget=40).run_episode(_Runner(), 0, 0).extra["rho"]
    early, late = np.mean(rho[:10]), np.mean(rho[-10:])
    assert late < early


def test_a_bad_threshold_is_refused_naming_the_option():
    with pytest.raises(UserInputError, match="verifai_threshold"):
        _search("verifai_ce", verifai_threshold=float("nan"))


def test_bayesian_optimisation_runs_through_gpyopt():
    pytest.importorskip("GPyOpt")
    outcome = _search("verifai_bo", search_budget=8).run_episode(_Runner(), 0, 0)
    assert len(outcome.extra["rho"]) == 8 and outcome.extra["verifai_sampler"] == "bo"
