"""``genesis-rl benchmark --smoke``: the whole benchmark in about a minute, with a pair that fails by construction,
so that a regression in any metric the leaderboard reports changes a value this test checks."""

from __future__ import annotations

import json

from genesis_rl.benchmark.matrix import SMOKE
from genesis_rl.commands.cli import main


def test_the_smoke_benchmark_confirms_the_failure_it_is_built_to_find(tmp_path, capsys):
    out = tmp_path / "smoke"
    assert main(["benchmark", "--smoke", "--quiet", "--out", str(out)]) == 0
    board = json.loads((out / "leaderboard.json").read_text())
    weak, control = board["cells"]["latency_braking"], board["cells"]["builtin_braking"]
    # constant brakes the lead as hard as the domain allows from the first step: in both trials the lead is met
    # too late (trial 0 at step 101, trial 1 at 106), inside the trigger region, a failure a careful driver
    # avoids, and every re-run on fresh world seeds fails again. (Trial 1's knob had braked the neighbour in the
    # next lane, which a straight corridor crossed on the bend, and it did not fail.) The smoke's figures are
    # these exact values, so that a metric that drifts fails here
    hit = weak["constant"]
    assert hit["episodes"] == SMOKE.trials * SMOKE.scenes == 2 and hit["reached"] == 2
    assert hit["falsified"] == hit["reported_failures"] == hit["triggered"] == 2
    assert hit["confirmed"] == hit["reproducible"] == 2 and hit["confirmed_rate"] == 1.0
    assert hit["reproduction_rate"] == 1.0 and hit["confirmed_ci"] == [0.1581, 1.0]
    assert hit["median_steps_to_failure"] == 101.0
    # sunny never brakes the lead: nothing reached, nothing failed, nothing re-run
    calm = weak["sunny"]
    assert calm["falsified"] == calm["reached"] == calm["confirmed"] == 0 and calm["reproduction_rate"] is None
    # the control meets the same braking in time: no false alarm from either policy
    assert all(c["falsified"] == c["false_alarm_candidates"] == c["confirmed"] == 0 for c in control.values())
    assert board["ranks"]["average_rank"] == {"sunny": 2.0, "constant": 1.0}
    again = json.loads((out / "reproductions" / "latency_braking" / "trial_00.json").read_text())
    runs = again["policies"]["constant"]["1019"]["runs"]
    assert again["reruns"] == SMOKE.reruns == len(runs) and all(r["reproduced"] for r in runs)
    assert all(abs(r["failure_at"] - 100) <= 1 for r in runs)  # the same impact, within a step, in other worlds
    second = json.loads((out / "reproductions" / "latency_braking" / "trial_01.json").read_text())
    assert [r["failure_at"] for r in second["policies"]["constant"]["567"]["runs"]] == [106, 106]
    printed = json.loads(capsys.readouterr().out.split("\nleaderboard:")[0])
    assert printed["cells"]["latency_braking"]["constant"]["confirmed_rate"] == 1.0
