"""Go-Explore (``goexplore``): it opens every start stratum, returns to promising cells from snapshots instead of
replaying them, stops at the first in-ODD failure, reports it replayed from the start, and stays in its budget."""

from __future__ import annotations

import copy
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from genesis_rl.adversaries import EpisodeOutcome, GoExplore, PolicyContext
from genesis_rl.adversaries.goexplore import bearing_sector
from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.loop.rules.danger import danger
from genesis_rl.sim.interface import SnapshotUnsupported

STEPS = 128
HEADING = 90.0  # the toy ego drives north


def _record(step: int, gap: float, collided: bool, start: dict) -> SimpleNamespace:
    return SimpleNamespace(
        step=step, knobs=dict(start), conditions=None, odd_status="inside",
        ego=SimpleNamespace(speed=10.0), collision=SimpleNamespace(collided=collided),
        lead=SimpleNamespace(present=True, true_distance=gap, speed=10.0 - (1.0 if gap < 40 else 0.0),
                             detected=gap >= 40), reward={"reward": 0.0})


class ToyWorld:
    """A lead 40 m ahead that the system loses only with the sun low (0-6 deg) and within 30 deg ahead; then the
    ego closes 1 m a step while the weather is left alone (a zero action) and the gap opens 2 m a step when the
    first knob is turned up. A collision takes about 40 steps of mostly leaving it be, in one of 48 strata."""

    held_knobs = ("sun_altitude_angle", "sun_azimuth_angle")
    knobs = ("fog_density", "sun_altitude_angle", "sun_azimuth_angle")
    heading_deg = HEADING

    def __init__(self) -> None:
        self.begun = 0
        self.restored = 0
        self.state = {"t": 0, "gap": 40.0, "start": {}}

    def start_from(self, position):  # noqa: ANN001, ANN201
        return {"sun_altitude_angle": -90.0 + 180.0 * position[0], "sun_azimuth_angle": 360.0 * position[1]}

    def natural_start(self, rng):  # noqa: ANN001, ANN201
        raise AssertionError("goexplore draws its own starts")

    def begin(self, scene, episode_seed, start=None) -> None:  # noqa: ANN001
        self.begun += 1
        self.state = {"t": 0, "gap": 40.0, "start": dict(start or {"sun_altitude_angle": 45.0,
                                                                  "sun_azimuth_angle": 0.0})}

    @property
    def blinded(self) -> bool:
        s = self.state["start"]
        return 0.0 <= s["sun_altitude_angle"] < 6.0 and bearing_sector(s["sun_azimuth_angle"], HEADING) == 0

    @property
    def steps_taken(self) -> int:
        return int(self.state["t"])

    def step(self, action: np.ndarray) -> SimpleNamespace:
        s = self.state
        s["t"] += 1
        if self.blinded:
            s["gap"] = min(40.0, s["gap"] + (2.0 if action[0] > 0.3 else -1.0))
        return _record(s["t"], s["gap"], s["gap"] <= 0.0, s["start"])

    def snapshot(self) -> dict:
        return copy.deepcopy(self.state)

    def restore(self, snapshot) -> None:  # noqa: ANN001
        self.restored += 1
        self.state = copy.deepcopy(snapshot)

    def run(self, act, scene, episode_seed, start=None) -> EpisodeOutcome:  # noqa: ANN001
        self.begin(scene, episode_seed, start)
        records = []
        for _ in range(STEPS):
            records.append(self.step(act(None)))
        return EpisodeOutcome(records, sim_steps=STEPS)


def _explore(seed: int, budget: int = 8, start: str = "natural") -> tuple[EpisodeOutcome, ToyWorld]:
    world = ToyWorld()
    policy = GoExplore(PolicyContext(action_dim=3, seed=seed,
                                     options={"search_budget": budget, "steps": STEPS, "start": start}))
    return policy.run_episode(world, scene=0, episode_seed=seed), world


def test_it_finds_the_one_stratum_that_fails_and_replays_it_from_the_start() -> None:
    found = restored = 0
    for seed in range(10):
        outcome, world = _explore(seed)
        extra = outcome.extra
        assert extra["strata"] == 48  # six bearing sectors x eight altitude bands
        assert outcome.sim_steps == sum(extra["candidate_steps"]) <= 8 * STEPS
        if extra["found_at_step"] is not None:
            found += 1
            assert extra["replay_exact"] is True
            first = next(i for i, r in enumerate(outcome.records) if r.collision.collided)
            assert first == extra["found_at_step"]
        restored += world.restored
    assert found >= 9
    assert restored > 0  # it returned to cells rather than replaying the steps that reached them


def test_random_starts_at_the_same_budget_rarely_find_it() -> None:
    """The reference: 8 episodes from uniformly drawn starts land in the failing stratum with p = 1/12 * 1/6 each."""
    rng = np.random.default_rng(0)
    hits = sum(any(0.0 <= rng.uniform(-90, 90) < 6.0 and bearing_sector(rng.uniform(0, 360), HEADING) == 0
                   for _ in range(8)) for _ in range(1000))
    assert hits / 1000 < 0.1


def test_the_same_seed_explores_the_same_way() -> None:
    a, _ = _explore(3)
    b, _ = _explore(3)
    assert a.extra == b.extra and repr(a.records) == repr(b.records)


def test_a_fixed_start_has_one_stratum_and_no_restarts() -> None:
    outcome, world = _explore(0, start="fixed")
    assert outcome.extra["strata"] == 1 and outcome.extra["rerooted"] == 0
    assert outcome.extra["found_at_step"] is None  # the fixed start (noon) never blinds the toy system


def test_danger_is_the_needed_deceleration_over_a_hard_braking_plus_a_missed_lead() -> None:
    rec = _record(5, 20.0, False, {})
    rec.lead.detected, rec.ego.speed, rec.lead.speed = True, 16.0, 10.0
    assert danger(rec) == pytest.approx(6.0 ** 2 / (2 * 20.0) / 6.0)
    rec.lead.detected = False
    assert danger(rec) == pytest.approx(0.15 + 0.5)
    assert danger(_record(5, 0.0, True, {})) == 2.5
    rec.lead.true_distance = math.nan
    assert danger(rec) == 0.0
    assert [bearing_sector(HEADING + b, HEADING) for b in (0, 29, -29, 31, 180, -31)] == [0, 0, 0, 1, 3, 5]


def test_a_runner_without_snapshots_is_refused_with_the_backends_reason() -> None:
    class Carlaish(ToyWorld):
        def snapshot(self) -> dict:
            raise SnapshotUnsupported("snapshots: the CARLA backend cannot save and restore a running world")

    policy = GoExplore(PolicyContext(action_dim=3, seed=0, options={"search_budget": 4, "steps": STEPS}))
    with pytest.raises(SnapshotUnsupported, match="CARLA backend cannot save"):
        policy.run_episode(Carlaish(), scene=0, episode_seed=0)
    with pytest.raises(UserInputError, match="search_budget = 1 must be >= 2"):
        GoExplore(PolicyContext(action_dim=3, seed=0, options={"search_budget": 1}))


@pytest.mark.render
def test_goexplore_on_lite_spends_at_most_its_budget_and_explores_the_same_way_twice(tmp_path) -> None:
    args = ["evaluate", "--policies", "goexplore", "--map", "urban", "--scenes", "1", "--steps", "20", "--seed", "2",
            "--search-budget", "4", "--odd", "genesis_rl/sut/zoo/odd/urban_any_hour.toml", "--dynamics", "natural",
            "--start", "natural", "--quiet", "--no-report"]
    rows = []
    for name in ("a", "b"):
        assert main([*args, "--out", str(tmp_path / name)]) == 0
        rows.append(json.loads(next((tmp_path / name / "episodes" / "goexplore").glob("*.json")).read_text()))
    extra = rows[0]["extra"]
    assert extra["strata"] == 48 and rows[0]["steps"] == 20
    assert rows[0]["sim_steps"] == sum(extra["candidate_steps"]) <= 4 * 20
    assert extra["candidate_steps"][-1] == 20  # the report: the chosen chain replayed from the start
    assert rows[0]["extra"] == rows[1]["extra"] and rows[0]["return"] == rows[1]["return"]


def test_a_world_where_every_start_crashes_outside_the_odd_ends_the_search_cleanly() -> None:
    """Nothing is archived after a crash, so nothing can be returned to: the search stops and still reports."""
    class Hostile(ToyWorld):
        def step(self, action: np.ndarray) -> SimpleNamespace:
            rec = super().step(action)
            rec.collision.collided, rec.odd_status = True, "outside"
            return rec

    policy = GoExplore(PolicyContext(action_dim=3, seed=0, options={"search_budget": 4, "steps": STEPS,
                                                                    "start": "natural"}))
    outcome = policy.run_episode(Hostile(), scene=0, episode_seed=0)
    assert outcome.extra["found_at_step"] is None and outcome.extra["archive_cells"] == 0
    assert outcome.extra["candidate_steps"] == [1] * 48 + [STEPS]  # one step a root, then the report
