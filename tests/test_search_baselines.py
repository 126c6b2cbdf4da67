"""The peer search baseline (cross-entropy, as VerifAI's sampler) and the constant-corner search: inside the
ODD, exactly their budget, deterministic."""

from __future__ import annotations

import json

import pyarrow.parquet as pq
import pytest

from genesis_rl.commands.cli import main

ODD = "configs/odd/highway_day.toml"


@pytest.mark.render
def test_cem_keeps_inside_the_odd_and_spends_exactly_its_budget(tmp_path) -> None:
    out = tmp_path / "cem"
    args = ["evaluate", "--policies", "cem", "--map", "highway", "--scenes", "1", "--steps", "20", "--seed", "3",
            "--search-budget", "5", "--odd", ODD, "--dynamics", "paper", "--quiet", "--no-report"]
    assert main([*args, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["policies"]["cem"]["sim_steps"] == 5 * 20  # 5 episodes of 20 steps, not 4 or 6
    row = json.loads(next((out / "episodes" / "cem").glob("*.json")).read_text())
    assert len(row["extra"]["search_returns"]) == 5 and row["extra"]["generations"] == [2, 3]
    assert max(row["extra"]["search_returns"]) == pytest.approx(row["return"], abs=1e-3)  # it reports its best
    steps = pq.read_table(next((out / "steps" / "cem").glob("*.parquet"))).to_pydict()
    assert set(steps["odd_status"]) <= {"inside", "boundary"}  # the paper's fast dynamics, held inside
    again = tmp_path / "again"
    assert main([*args, "--out", str(again)]) == 0
    assert json.loads(next((again / "episodes" / "cem").glob("*.json")).read_text())["extra"]["search_returns"] == \
        row["extra"]["search_returns"]


@pytest.mark.render
def test_corner_search_plays_every_corner_and_ranks_them() -> None:
    from genesis_rl.analysis.corners import corner_actions, search_corners
    from genesis_rl.env import GenesisEnv

    held = GenesisEnv(map="highway", scenes=2, dynamics="natural")  # the sun moves 0.1 deg an episode: held
    try:
        acts = corner_actions(held)
        assert len(acts) == 8 and all(a[3] == 0.0 and a[4] == 0.0 for a in acts)
        assert {tuple(a[:3]) for a in acts} == {(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)}
    finally:
        held.close()
    env = GenesisEnv(map="highway", scenes=2, knobs=("fog_density", "precipitation"), episode_steps=6)
    try:
        rows = search_corners(env, [0, 1], [5, 6])
    finally:
        env.close()
    assert sorted(tuple(r["action"]) for r in rows) == [(-1, -1), (-1, 1), (1, -1), (1, 1)]
    means = [r["mean_return"] for r in rows]
    assert means == sorted(means, reverse=True) and all(len(r["returns"]) == 2 for r in rows)
    assert rows[0]["mean_return"] == pytest.approx(sum(rows[0]["returns"]) / 2, abs=1e-3)


class _CornerRunner:
    """What corner_search sees of an episode runner: it records each candidate's start and action."""

    held_knobs = ("sun_altitude_angle",)
    knobs = ("fog_density", "precipitation", "sun_altitude_angle")
    has_start_head = False
    last_record = None

    def __init__(self) -> None:
        self.played: list[tuple[tuple[float, ...], tuple[float, ...]]] = []

    def held_indices(self) -> list[int]:
        return [2]

    def start_from(self, position):
        return tuple(position)

    def run(self, act, scene, episode_seed, start=None, start_head=False):
        from genesis_rl.adversaries import EpisodeOutcome

        action = tuple(float(v) for v in act(None))
        self.played.append((start, action))
        return EpisodeOutcome([], sim_steps=10)


def test_corner_search_plays_every_corner_within_its_budget_and_a_seeded_draw_beyond_it() -> None:
    from genesis_rl.adversaries import CornerSearch, PolicyContext

    runner = _CornerRunner()
    CornerSearch(PolicyContext(3, seed=0, options={"search_budget": 8, "start": "natural"})).run_episode(runner, 4, 9)
    assert sorted(a for _, a in runner.played) == [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    # a held knob starts at the end its action names: the sun at the ODD's low or high bound
    assert all(start == ((a[2] + 1.0) / 2.0,) for start, a in runner.played)
    few = CornerSearch(PolicyContext(3, seed=0, options={"search_budget": 3}))
    picked = few.corners(4, 9)
    assert len(set(picked)) == 3 and picked == few.corners(4, 9) and picked != few.corners(5, 9)
    runner = _CornerRunner()
    outcome = few.run_episode(runner, 4, 9)
    assert outcome.sim_steps == 30 and all(start is None for start, _ in runner.played)  # fixed start: none chosen
    assert outcome.extra["corners"] == picked
