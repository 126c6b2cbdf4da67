"""The metrics of a falsifier: Kaplan-Meier checked by hand, trials on crafted records (a known step of first
failure, censoring at the budget, reached but not triggered, a failure outside the ODD), and a real campaign
of a blind system inside highway_day whose two in-ODD crashes the metrics must find at their recorded steps."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.benchmark.metrics import Trial, falsifier_metrics, in_odd_failure_at, policy_metrics, trial_of
from genesis_rl.benchmark.survival import kaplan_meier, median_time
from genesis_rl.campaigns.campaign import run_campaign
from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.zoo import EMPTY, Bound, TriggerRegion, ZooMember, env_settings, zoo_member
from genesis_rl.world.odd.conditions import Conditions
from genesis_rl.world.step_record import CollisionStep, StepRecord, synthetic_step

CLEAR = Conditions(3000.0, 0.0, "dry", "day", False)


def _episode(n: int, *, low_sun_from: int | None = None, hits: dict[int, str] | None = None) -> list[StepRecord]:
    """``n`` steps at 40 deg of sun, below 15 deg from ``low_sun_from``; ``hits``: step index -> the ODD status
    of a step in contact with another vehicle (others are inside and not in contact)."""
    hits = hits or {}
    out = []
    for i in range(n):
        sun = 5.0 if low_sun_from is not None and i >= low_sun_from else 40.0
        rec = replace(synthetic_step(i + 1, knobs={"sun_altitude_angle": sun}), conditions=CLEAR,
                      odd_status=hits.get(i, "inside"))
        if i in hits:
            rec = replace(rec, collision=CollisionStep(True, 5.0, 7))
        out.append(rec)
    return out


def test_kaplan_meier_by_hand_with_censoring() -> None:
    # at 2: 5 at risk, 1 fails -> 4/5; at 3: 4 at risk (the one censored at 3 counts), 1 fails -> 0.8 * 3/4;
    # at 5: 2 at risk, 1 fails -> 0.6 * 1/2; the one censored at 6 adds no step
    t, s = kaplan_meier([2, 3, 3, 5, 6], [True, True, False, True, False])
    assert t.tolist() == [0.0, 2.0, 3.0, 5.0]
    assert np.allclose(s, [1.0, 0.8, 0.6, 0.3])
    assert median_time(t, s) == 5.0
    t, s = kaplan_meier([40, 40], [False, False])  # nothing failed within the budget
    assert t.tolist() == [0.0] and s.tolist() == [1.0] and median_time(t, s) is None
    with pytest.raises(ValueError, match="one length"):
        kaplan_meier([1, 2], [True])


def test_an_in_odd_failure_is_a_collision_that_began_inside_the_odd() -> None:
    assert in_odd_failure_at(_episode(10)) is None
    # contact from 3 (outside) on to 4 (inside) is one collision, begun outside; the next one begins on the boundary
    assert in_odd_failure_at(_episode(10, hits={3: "outside", 4: "inside", 7: "boundary"})) == 7
    assert in_odd_failure_at(_episode(10, hits={0: "inside"})) == 0


def test_trials_on_crafted_records() -> None:
    region = zoo_member("low_sun").trigger
    known = trial_of(1, _episode(20, low_sun_from=4, hits={9: "inside"}), region)
    assert (known.reached_at, known.failure_at, known.triggered, known.steps_to_failure) == (4, 9, True, 10)
    censored = trial_of(2, _episode(20), region)
    assert (censored.failed, censored.reached, censored.steps_to_failure) == (False, False, 20)
    reached_only = trial_of(3, _episode(20, low_sun_from=12), region)
    assert (reached_only.reached, reached_only.triggered, reached_only.steps_to_failure) == (True, False, 20)
    early = trial_of(4, _episode(20, low_sun_from=12, hits={5: "inside"}), region)  # failed before it reached
    assert (early.failed, early.reached, early.triggered) == (True, True, False)
    outside = trial_of(5, _episode(20, low_sun_from=0, hits={6: "outside"}), region)  # not inside the ODD
    assert (outside.failed, outside.triggered, outside.steps_to_failure) == (False, False, 20)


def test_a_search_trial_counts_every_candidate_before_its_first_failure() -> None:
    """ARCH-COMP's simulations to the first falsification: a search that failed in its second of three 20-step
    candidates spent 20 + 6 steps to it, whichever episode it reports; its budget is all 60."""
    region = zoo_member("low_sun").trigger
    row = {"extra": {"candidate_steps": [20, 20, 20], "candidate_failures": [None, 5, 3]}}
    reported = trial_of(1, _episode(20, low_sun_from=0, hits={3: "inside"}), region, row)  # it reports the third
    assert (reported.steps, reported.failure_at, reported.steps_to_failure, reported.failed) == (60, 3, 26, True)
    quiet = {"extra": {"candidate_steps": [20, 20], "candidate_failures": [None, None]}}
    none = trial_of(2, _episode(20), region, quiet)
    assert (none.failed, none.steps_to_failure) == (False, 40)  # censored at everything it spent
    ledger = {"extra": {"candidate_steps": [20, 20], "candidate_failures": [7, None]}}
    hidden = trial_of(3, _episode(20), region, ledger)
    assert (hidden.failed, hidden.failure_at, hidden.steps_to_failure) == (True, None, 8)  # a candidate failed
    old = trial_of(4, _episode(20, hits={9: "inside"}), region, {"extra": {"search_returns": [1.0, 2.0]}})
    assert (old.steps, old.steps_to_failure) == (20, 10)  # a campaign before the ledger: the reported episode


def test_a_failure_the_careful_driver_could_not_avoid_is_not_avoidable() -> None:
    """Issue 32: an unavoidable failure is never the system's. It still counts as a falsification (a collision
    inside the ODD happened), and the trial says it was not avoidable, for a step policy and a search alike."""
    region = zoo_member("low_sun").trigger
    records = _episode(20, low_sun_from=0, hits={9: "inside"})
    blamed = {"failure": {**_failure(10), "blame": "unavoidable"}}
    hard = trial_of(1, records, region, blamed)
    assert (hard.failed, hard.unavoidable, hard.avoidable, hard.triggered) == (True, True, False, True)
    assert trial_of(2, records, region, {"failure": _failure(10)}).avoidable  # blamed on perception
    assert trial_of(3, records, region).avoidable  # no blame recorded: counted as the system's
    out_of_odd = {"failure": {**_failure(10), "blame": "unavoidable", "odd_status": "outside"}}
    outside = trial_of(4, _episode(20, hits={9: "outside"}), region, out_of_odd)
    assert (outside.failed, outside.unavoidable) == (False, False)  # not an in-ODD failure at all
    search = {**blamed, "extra": {"candidate_steps": [20, 20], "candidate_failures": [None, 9]}}
    assert trial_of(5, records, region, search).avoidable is False  # as its reported episode says


def _row(scene: int, failure: dict | None) -> dict:
    return {"scene": scene, "episode_seed": scene, "naturalness": {"ratio_to_held": 0.0}, "failure": failure}


def _failure(step: int) -> dict:
    return {"step": step, "mode": "non_detection", "blame": "perception", "odd_status": "inside",
            "visibility": ">=500 m", "rain": "no rain", "light": "day", "road_state": "dry", "hit": "lead",
            "naturalness": 0.0, "oracle_collides": False}


TRIALS = (Trial(1, 20, 4, 9), Trial(2, 20, None, None), Trial(3, 20, 12, None), Trial(4, 20, None, 5))
ROWS = (_row(1, _failure(10)), _row(2, None), _row(3, None), _row(4, {**_failure(6), "hit": "other vehicle"}))


def test_policy_metrics_on_crafted_trials() -> None:
    m = policy_metrics("random", zoo_member("low_sun"), TRIALS, ROWS)
    assert (m.falsified, m.falsification_rate, m.reached, m.reached_share, m.triggered, m.triggered_share) == (
        2, 0.5, 2, 0.5, 1, 0.25)
    # steps to failure 10, 20 (censored), 20 (censored), 6: at 6, 4 at risk -> 3/4; at 10, 3 at risk -> 1/2
    assert m.survival == ((0.0, 1.0), (6.0, 0.75), (10.0, 0.5))
    assert m.median_steps_to_failure == 10.0
    assert m.distinct_in_odd_failures == 2  # a lead and another vehicle: two clusters
    assert m.false_alarm_candidates == ()  # a weakness: failures are findings
    d = m.as_dict()
    assert json.loads(json.dumps(d)) == d
    assert [t["steps_to_failure"] for t in d["trials"]] == [10, 20, 20, 6]
    assert d["falsification_ci"][0] < 0.5 < d["falsification_ci"][1]


def test_on_a_control_every_in_odd_failure_is_a_false_alarm_candidate() -> None:
    m = policy_metrics("random", zoo_member("oracle_highway"), TRIALS, ROWS)
    assert m.kind == "control" and m.falsified == 2
    assert [(a["scene"], a["step_index"], a["blame"]) for a in m.false_alarm_candidates] == [
        (1, 9, "perception"), (4, 5, "perception")]


def test_a_control_counts_the_false_alarms_beyond_those_sunny_has_on_the_same_scenes() -> None:
    from genesis_rl.benchmark.leaderboard import pooled

    member = zoo_member("oracle_highway")
    adversary = policy_metrics("random", member, TRIALS, ROWS)  # in-ODD failures on scenes 1 and 4
    # sunny (the held start weather) fails on scene 4 as well: a failure the system has whatever the weather
    sunny = policy_metrics("sunny", member, (Trial(1, 20, None, None), Trial(4, 20, None, 7)),
                           (_row(1, None), _row(4, _failure(8))))
    cell = pooled("random", "oracle_highway", [adversary], baseline=[sunny])
    assert (cell["false_alarm_candidates"], cell["false_alarms_beyond_sunny"]) == (2, 1)
    assert pooled("random", "oracle_highway", [adversary])["false_alarms_beyond_sunny"] is None  # no sunny played


# -- a real campaign ---------------------------------------------------------------------------------------
#: the blind system (no detections) inside highway_day: it hits its lead in clear noon on scenes 3 and 5 of a
#: six-scene catalog (the campaign's seed 4 picks them; tests/test_natural_campaign.py)
BLIND = ZooMember(name="blind_highway", kind="weakness", summary="test only", system="blind", odd="highway_day.toml",
                  map="highway", trigger=TriggerRegion((Bound("visibility_m", 2000.0),)), env={"dynamics": "natural"})


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> str:
    path = str(tmp_path_factory.mktemp("zoo") / "highway6.json")
    assert main(["scenes", "--map", "highway", "--count", "6", "--seed", "0", "--out", path]) == 0
    return path


@pytest.fixture(scope="module")
def blind_campaign(catalog: str, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("zoo") / "blind"
    spec = CampaignSpec(policies=("sunny",), map="highway", catalog=catalog, scenes=2, seed=4, steps=160,
                        env=env_settings(BLIND))
    run_campaign(spec, out, progress=False)
    return out


def test_metrics_find_the_blind_systems_crashes_at_their_recorded_steps(blind_campaign: Path) -> None:
    m = falsifier_metrics(blind_campaign, BLIND)["sunny"]
    rows = [json.loads(p.read_text()) for p in sorted((blind_campaign / "episodes" / "sunny").glob("*.json"))]
    assert [t.scene for t in m.trials] == [r["scene"] for r in rows] == [3, 5]
    # a record's step counts from 1: steps to the failure are the row's first collision step
    assert [t.steps_to_failure for t in m.trials] == [r["first_collision_step"] for r in rows]
    assert all(t.steps == 160 and t.reached_at == 0 and t.triggered for t in m.trials)  # clear air from the start
    assert (m.falsified, m.triggered, m.falsification_rate) == (2, 2, 1.0)
    first, second = sorted(r["first_collision_step"] for r in rows)
    assert m.survival == ((0.0, 1.0), (float(first), 0.5), (float(second), 0.0))
    summary = json.loads((blind_campaign / "summary.json").read_text())
    assert m.distinct_in_odd_failures == summary["policies"]["sunny"]["natural"]["distinct_in_odd_failures"] >= 1


def test_failures_outside_the_region_are_not_triggered(blind_campaign: Path) -> None:
    fog = replace(BLIND, trigger=TriggerRegion((Bound("visibility_m", high=150.0),)))
    m = falsifier_metrics(blind_campaign, fog)["sunny"]
    assert (m.falsified, m.reached, m.triggered) == (2, 0, 0)  # found, but not the stated weakness
    control = falsifier_metrics(blind_campaign, replace(BLIND, kind="control", trigger=EMPTY))["sunny"]
    assert control.reached == control.triggered == 0  # an empty region is never reached
    assert [(a["blame"], a["oracle_collides"]) for a in control.false_alarm_candidates] == [("perception", False)] * 2


def test_a_campaign_of_another_system_is_refused_naming_the_field(blind_campaign: Path) -> None:
    with pytest.raises(UserInputError, match="not run on zoo member 'builtin_highway': its system is 'blind', the "
                                             "member's 'builtin'"):
        falsifier_metrics(blind_campaign, "builtin_highway")
    with pytest.raises(UserInputError, match="its traffic is 'mixed', the member's 'free_flow'"):
        falsifier_metrics(blind_campaign, replace(BLIND, traffic="free_flow"))


def test_a_campaign_spec_carries_its_traffic_and_older_specs_read_the_same() -> None:
    """traffic is written only when not mixed, so a campaign.json of before reads (and resumes) unchanged."""
    from genesis_rl.campaigns.campaign_spec import CampaignSpec

    mixed = CampaignSpec(policies=("sunny",))
    assert "traffic" not in mixed.to_json() and CampaignSpec.from_json(mixed.to_json()) == mixed
    free = CampaignSpec(policies=("sunny",), traffic="free_flow")
    assert free.to_json()["traffic"] == "free_flow" and CampaignSpec.from_json(free.to_json()) == free
    with pytest.raises(UserInputError, match="spec.traffic = 'jam'; allowed: mixed, free_flow"):
        CampaignSpec(policies=("sunny",), traffic="jam")
    with pytest.raises(UserInputError, match="a catalog file .* brings its own"):
        CampaignSpec(policies=("sunny",), traffic="free_flow", catalog="c.json")


def test_a_control_campaign_censors_every_trial_at_the_budget(catalog: str, tmp_path) -> None:
    member = zoo_member("builtin_highway")
    spec = CampaignSpec(policies=("sunny",), map=member.map, catalog=catalog, scenes=2, seed=4, steps=40,
                        env=env_settings(member))
    run_campaign(spec, tmp_path / "control", progress=False)
    m = falsifier_metrics(tmp_path / "control", "builtin_highway")["sunny"]
    assert [(t.steps, t.failed, t.steps_to_failure) for t in m.trials] == [(40, False, 40)] * 2
    assert m.survival == ((0.0, 1.0),) and m.median_steps_to_failure is None
    assert (m.falsification_rate, m.distinct_in_odd_failures, m.false_alarm_candidates) == (0.0, 0, ())
