"""The peer search baseline (cross-entropy, as VerifAI's sampler) and the constant-corner search: inside the
ODD, exactly their budget, deterministic."""

from __future__ import annotations

import json

import pyarrow.parquet as pq
import pytest

from genesis_rl.cli import main

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
