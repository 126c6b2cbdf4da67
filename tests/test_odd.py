"""Natural edge cases: conditions in physical units, the ODD contract, natural dynamics, naturalness, the
speed-for-visibility rule, blame evidence and distinct-failure clustering (no simulator needed here)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.labels.blame import blame_label, visibility_evidence
from genesis_rl.labels.distinct import clusters, failure_key, natural_summary, rain_band, visibility_band
from genesis_rl.loop.rules.rulebook import SpeedForVisibilityRule, speed_for_visibility, stopping_distance_m
from genesis_rl.world.knobs import KNOBS, PAPER_KNOBS, KnobActionMapper, Weather
from genesis_rl.world.odd.conditions import (
    Conditions,
    ConditionsModel,
    conditions_model,
    rain_rate_mm_h,
    road_state,
    sun_glare,
)
from genesis_rl.world.odd.domain import ODD, Range, check_start, load_odd, parse_odd
from genesis_rl.world.odd.dynamics import NATURAL_RATES, WeatherModel, max_deltas
from genesis_rl.world.step_record import PerceptionStep, RecordedBox, StepRecord, synthetic_step

LITE = conditions_model("lite")


def clear(**knobs: float) -> Weather:
    return Weather.preset("clear_noon").replace(**knobs)


# -- conditions --------------------------------------------------------------------------------------------------
def test_visibility_is_koschmieder_of_fog_rain_and_haze():
    # fog 30 % alone: the calibration table's 120 m, plus clear-air haze (3.912 / 3000 per metre)
    beta = 3.912 / 120.0 + 0.0  # the table gives fog + haze at 30 %
    assert LITE.visibility_m(clear(fog_density=30)) == pytest.approx(3.912 / beta, rel=1e-9)
    # rain 100 % alone: 150 m by construction (rain extinction added to clear air)
    assert LITE.visibility_m(clear(precipitation=100)) == pytest.approx(150.0, rel=1e-9)
    # both: extinctions add: 1 / V = 1 / V_fog + 1 / V_rain - 1 / V_clear
    v = LITE.visibility_m(clear(fog_density=30, precipitation=100))
    assert 1 / v == pytest.approx(1 / 120 + 1 / 150 - 1 / 3000, rel=1e-9)
    assert LITE.visibility_range_m == pytest.approx((1 / (1 / 12 + 1 / 150 - 1 / 3000), 3000.0), rel=1e-9)


def test_rain_rate_road_light_and_glare_mappings():
    assert rain_rate_mm_h(0) == 0 and rain_rate_mm_h(30) == 2.5 and rain_rate_mm_h(50) == 7.6
    assert rain_rate_mm_h(40) == pytest.approx((2.5 + 7.6) / 2) and rain_rate_mm_h(100) == 50
    assert [road_state(d, 0) for d in (0, 10, 30, 70)] == ["dry", "damp", "wet", "standing_water"]
    assert road_state(0, 90) == "wet"  # wet surfaces without standing water
    c = LITE.conditions(clear(sun_altitude_angle=-5))
    assert c.light == "twilight" and LITE.conditions(clear(sun_altitude_angle=-20)).light == "night"
    low_sun = clear(sun_altitude_angle=10, sun_azimuth_angle=90)
    assert sun_glare(low_sun, 80.0, cloud_cover=0.05)  # 10 degrees off the heading
    assert not sun_glare(low_sun, 140.0, cloud_cover=0.05)  # 50 degrees off
    assert not sun_glare(low_sun, 90.0, cloud_cover=0.9)  # overcast
    assert not sun_glare(clear(sun_azimuth_angle=90), 90.0, cloud_cover=0.05)  # sun high at 75 degrees
    assert sun_glare(clear(sun_altitude_angle=10, sun_azimuth_angle=355), 5.0, cloud_cover=0.0)  # across 0/360


# -- the ODD file ------------------------------------------------------------------------------------------------
HIGHWAY = {"visibility": {"min": 150, "unit": "m"}, "rain_rate": {"max": 7.6, "unit": "mm/h"},
           "road_state": {"allowed": ["dry", "damp", "wet"]}, "light": {"allowed": ["day"]},
           "sun_glare": {"allowed": False}}


def test_shipped_odds_load_and_label():
    for name in ("highway_day", "urban_all_day"):
        odd = load_odd(f"configs/odd/{name}.toml", LITE)
        assert odd.name == name
        check_start(odd, Weather.preset("clear_noon"), LITE)
    odd = parse_odd(HIGHWAY, "t")
    assert odd.status(LITE.conditions(clear())) == "inside"
    assert odd.status(LITE.conditions(clear(fog_density=25))) == "boundary"  # ~158 m: within 10 % of 150
    assert odd.status(LITE.conditions(clear(fog_density=35))) == "outside"
    assert odd.violations(LITE.conditions(clear(sun_altitude_angle=-20))) == ["light 'night' not in ['day']"]
    high_sun = parse_odd({**HIGHWAY, "sun_altitude": {"min": 15, "unit": "deg"}}, "t")  # bounded on the weather
    low = clear(sun_altitude_angle=10, sun_azimuth_angle=200)
    assert high_sun.status(LITE.conditions(low), low) == "outside" and odd.status(LITE.conditions(low), low) == "inside"
    assert high_sun.describe()["sun_altitude"] == {"min": 15.0, "max": 90.0, "unit": "deg"}
    assert "sun_altitude" not in odd.describe()  # domains without one describe as before


@pytest.mark.parametrize("data, message", [
    ({"humidity": {"max": 3}}, "unknown quantity or key(s) ['humidity']; allowed: visibility, rain_rate"),
    ({"visibility": {"min": 300, "max": 100, "unit": "m"}}, "visibility: min 300 > max 100: the domain is empty"),
    ({"visibility": {"min": 150}}, "visibility: unit is missing; allowed: unit = \"m\""),
    ({"visibility": {"min": 150, "unit": "km"}}, "visibility: unit = 'km'; allowed: \"m\""),
    ({"visibility": {"min": 5000, "unit": "m"}}, "out of reach of the 'lite' backend, which shows 11..3000 m"),
    ({"light": {"allowed": ["dawn"]}}, "light: unknown value(s) ['dawn']; allowed: day, twilight, night"),
    ({"road_state": {"allowed": []}}, "road_state: allowed is empty"),
    ({"rain_rate": {"max": "a lot", "unit": "mm/h"}}, "rain_rate.max = 'a lot' must be a finite number"),
    ({"sun_glare": {"allowed": "no"}}, "sun_glare must be a table with allowed = true or false"),
    ({"sun_altitude": {"min": 15}}, "sun_altitude: unit is missing; allowed: unit = \"deg\""),
    ({"sun_altitude": {"min": 15, "unit": "rad"}}, "sun_altitude: unit = 'rad'; allowed: \"deg\""),
    ({"sun_altitude": {"min": 120, "unit": "deg"}}, "sun_altitude.min = 120"),
    ({"sun_altitude": {"min": 30, "max": 10, "unit": "deg"}}, "sun_altitude: min 30 > max 10: the domain is empty"),
    ({"sun_altitude": {"low": 3, "unit": "deg"}}, "sun_altitude: unknown key(s) ['low']; allowed: min, max, unit"),
    ({"sun_altitude": {"unit": "deg"}}, "sun_altitude: give min, max or both [deg]"),
])
def test_bad_odd_files_name_the_field(data, message):
    with pytest.raises(UserInputError, match="ODD 'bad.toml'") as err:
        parse_odd(data, "bad.toml", LITE)
    assert message in str(err.value)


def test_an_odd_that_excludes_the_start_weather_is_refused():
    with pytest.raises(UserInputError, match=r"start weather is outside the ODD 't'.*visibility 18 m not in "
                                             r"\[150, inf\]"):
        check_start(parse_odd(HIGHWAY, "t"), Weather.preset("dense_fog"), LITE)


def test_keep_inside_never_leaves_the_odd_under_thousands_of_random_steps():
    odd = parse_odd(HIGHWAY, "t")
    for dynamics in ("paper", "natural"):
        mapper = KnobActionMapper(PAPER_KNOBS, max_delta=max_deltas(PAPER_KNOBS, dynamics, 0.05, 0.05))
        rng = np.random.default_rng(1)
        w = clear()
        reached_bound = 0
        for step in range(3000):
            heading = float(rng.uniform(0, 360))
            action = np.clip(rng.normal(0.6, 1.0, 5), -1, 1)  # biased toward fog, rain, water, sunset
            proposed = mapper.apply(w, action)
            w = odd.keep_inside(w, proposed, LITE, heading)
            c = LITE.conditions(w, heading)
            assert odd.contains(c), (dynamics, step, c)
            reached_bound += odd.status(c) == "boundary"
        if dynamics == "paper":
            assert reached_bound > 1000  # it pushed against the bound, and rode along it


def test_keep_inside_moves_other_knobs_while_one_is_at_its_bound():
    odd = parse_odd(HIGHWAY, "t")
    w = clear(fog_density=26.0)  # near the 150 m bound
    proposed = w.replace(fog_density=40.0, precipitation_deposits=20.0)
    kept = odd.keep_inside(w, proposed, LITE)
    assert kept["precipitation_deposits"] == 20.0
    assert 26.0 < kept["fog_density"] < 40.0
    assert LITE.visibility_m(kept) == pytest.approx(150.0, rel=1e-3)


# -- dynamics and naturalness ---------------------------------------------------------------------------------
@pytest.mark.parametrize("dt", [0.01, 0.05, 0.1, 0.5])
def test_natural_rates_hold_per_second_at_any_step_length(dt):
    mapper = KnobActionMapper(PAPER_KNOBS, max_delta=max_deltas(PAPER_KNOBS, "natural", dt, 0.05))
    w = clear(sun_altitude_angle=40)
    steps = int(round(1.0 / dt))
    for _ in range(steps):  # one simulated second of full push
        w = mapper.apply(w, np.ones(5))
    start = clear(sun_altitude_angle=40)
    for k in PAPER_KNOBS:
        assert abs(w[k] - start[k]) == pytest.approx(NATURAL_RATES[k], rel=1e-9), k
    assert NATURAL_RATES["sun_altitude_angle"] * 60 == pytest.approx(0.25)  # 0.25 degrees a minute


def test_log_likelihood_of_a_hand_made_trajectory():
    model = WeatherModel(("fog_density", "precipitation"))
    dt = 0.5
    t = [{"fog_density": 0.0, "precipitation": 10.0}, {"fog_density": 1.0, "precipitation": 10.0},
         {"fog_density": 3.0, "precipitation": 9.0}]
    s_f, s_p = 4.0 * math.sqrt(dt), 2.0 * math.sqrt(dt)  # sigma * sqrt(dt)

    def logn(x, s):
        return -0.5 * math.log(2 * math.pi * s * s) - x * x / (2 * s * s)

    expected = -math.log(100) - math.log(100) + logn(1, s_f) + logn(0, s_p) + logn(2, s_f) + logn(-1, s_p)
    assert model.log_likelihood(t, dt) == pytest.approx(expected, rel=1e-12)
    assert model.naturalness(t, dt) == pytest.approx(-0.5 * ((1 / s_f) ** 2 + (2 / s_f) ** 2 + (1 / s_p) ** 2))
    drift = [{"fog_density": 2.0 * i, "precipitation": 0.0} for i in range(11)]
    jump = [{"fog_density": 0.0 if i < 10 else 20.0, "precipitation": 0.0} for i in range(11)]
    assert model.log_likelihood(jump, dt) < model.log_likelihood(drift, dt)  # same start and end
    az = WeatherModel(("sun_azimuth_angle",))
    assert az.naturalness([{"sun_azimuth_angle": 359.0}, {"sun_azimuth_angle": 1.0}], 1.0) == \
        pytest.approx(az.naturalness([{"sun_azimuth_angle": 1.0}, {"sun_azimuth_angle": 3.0}], 1.0))


# -- speed for visibility and blame -----------------------------------------------------------------------------
def fog_step(step: int, speed: float, visibility: float, road: str = "dry", **kw) -> StepRecord:
    rec = synthetic_step(step, ego_speed=speed, **kw)
    return replace(rec, conditions=Conditions(visibility, 0.0, road, "day", False))


def test_speed_for_visibility_rule_on_crafted_records():
    # UK Highway Code: 70 mph (31.3 m/s) stops in 21 m + 75 m = 96 m on a dry road
    assert stopping_distance_m(31.29) == pytest.approx(96, abs=1.5)
    assert stopping_distance_m(10, "wet") == pytest.approx(6.7 + 100 / 6.5)
    v = speed_for_visibility(40.0)
    assert stopping_distance_m(v) == pytest.approx(40.0)
    rule = SpeedForVisibilityRule()
    assert rule.term(fog_step(0, v - 1, 40.0)) == 0.0
    assert rule.term(fog_step(0, v + 2, 40.0)) == pytest.approx(2.0)
    assert rule.term(fog_step(0, v, 40.0, "wet")) > 0  # the same speed is too fast on a wet road
    assert rule.term(synthetic_step(0, ego_speed=30.0)) == 0.0  # no conditions recorded: no judgement


def _approach(speed: float, visibility: float, start_gap: float, steps: int = 60) -> list[StepRecord]:
    """The ego at constant ``speed`` closes on a stopped vehicle 1 from ``start_gap``; it hits at the end."""
    recs = []
    for i in range(steps):
        gap = max(0.0, start_gap - speed * 0.05 * i)
        hit = i == steps - 1
        rec = fog_step(i, speed, visibility, lead_gap=gap, lead_speed=0.0, collision=hit, collision_speed=speed)
        box = RecordedBox(1, (100, 100, 140, 130), gap, 1.0, False)
        recs.append(replace(rec, perception=PerceptionStep(0, 1, 0.0, (), (box,))))
    return recs


def test_a_crafted_fog_collision_is_not_stoppable_and_a_clear_one_is():
    # 12 m visibility at 15 m/s: the car ahead appears 12 m away; stopping needs 10 + 17 = 27 m
    fog = _approach(15.0, 12.0, start_gap=44.25)
    ev = visibility_evidence(fog, len(fog) - 1)
    assert ev["visible"] and not ev["stoppable"] and ev["distance_when_visible_m"] <= 12.0
    assert ev["too_fast_for_visibility_m_s"] > 5  # 15 m/s where 12 m of sight allows ~7
    assert blame_label(ev, oracle_collides=True) == "control"  # a driver would have slowed down
    # a cut-in 5 m ahead at 6 m/s in the same fog: the speed suits the fog, but 5 m is too short to stop
    cut_in = _approach(6.0, 12.0, start_gap=5.1, steps=18)
    ev = visibility_evidence(cut_in, len(cut_in) - 1)
    assert not ev["stoppable"] and ev["too_fast_for_visibility_m_s"] <= 0.5
    assert blame_label(ev, oracle_collides=True) == "unavoidable"
    # clear air: the same approach is seen from 44 m, with room to stop; ground truth avoids it
    clear_air = _approach(15.0, 3000.0, start_gap=44.25)
    ev = visibility_evidence(clear_air, len(clear_air) - 1)
    assert ev["visible"] and ev["stoppable"] and ev["distance_when_visible_m"] == pytest.approx(44.25)
    assert blame_label(ev, oracle_collides=False) == "perception"
    assert blame_label(ev, oracle_collides=True) == "control"


# -- distinct failures ------------------------------------------------------------------------------------------
def _failure(mode="non_detection", blame="perception", vis=120.0, rain=0.0, nat=-1.0, scene=1, hit="lead"):
    c = {"visibility_m": vis, "rain_mm_h": rain, "road_state": "dry", "light": "day", "sun_glare": False}
    return {"mode": mode, "blame": blame, "odd_status": "inside", "conditions": c, "visibility": visibility_band(vis),
            "rain": rain_band(rain), "light": "day", "road_state": "dry", "hit": hit, "naturalness": nat,
            "scene": scene, "speed": 10.0, "step": 100}


def test_near_identical_failures_cluster_and_different_ones_do_not():
    a, b = _failure(vis=120.0, nat=-5.0, scene=1), _failure(vis=110.0, nat=-2.0, scene=2)
    assert failure_key(a) == failure_key(b)
    groups = clusters([a, b])
    assert len(groups) == 1 and groups[0]["count"] == 2
    assert groups[0]["members"][0]["scene"] == 2  # the most natural one represents the cluster
    for other in (_failure(vis=40.0), _failure(blame="control"), _failure(mode="lost_detection"),
                  _failure(rain=10.0), _failure(hit="braking lead")):
        assert failure_key(other) != failure_key(a)
    assert len(clusters([a, b, _failure(vis=40.0), _failure(blame="control")])) == 3
    assert visibility_band(49.9) == "<50 m" and visibility_band(150.0) == "150-500 m"
    assert rain_band(0.0) == "no rain" and rain_band(2.4) == "light rain" and rain_band(60) == "violent rain"


def test_natural_summary_counts_in_odd_distinct_failures_and_blame():
    def row(scene, failure=None, status="inside"):
        f = None if failure is None else {**failure, "odd_status": status}
        return {"scene": scene, "episode_seed": scene, "failure": f, "naturalness": {"ratio_to_held": -1.0},
                "odd": {"inside": 10, "boundary": 0, "outside": 0}, "record": None}

    rows = [row(1, _failure(scene=1)), row(2, _failure(vis=100.0, scene=2)), row(3, _failure(blame="control")),
            row(4, _failure(), status="outside"), row(5), row(6)]
    n = natural_summary("random", rows)
    assert n["collisions"] == 4 and n["in_odd_collisions"] == 3 and n["distinct_in_odd_failures"] == 2
    assert n["blame"] == {"perception": 2, "control": 1, "unavoidable": 0}
    assert n["in_odd_collision_rate"]["rate"] == 0.5 and 0.11 < n["in_odd_collision_rate"]["ci_low"] < 0.12
    assert natural_summary("random", [{"scene": 1, "failure": None}]) is None  # a 0.5.0 campaign


def test_range_boundary_margin():
    r = Range(150.0, math.inf)
    assert r.near_bound(160.0, 0.1) and not r.near_bound(170.0, 0.1)
    r = Range(0.0, 7.6)
    assert r.near_bound(7.0, 0.1) and not r.near_bound(6.0, 0.1)


def test_odd_describe_round_trips():
    odd = load_odd("configs/odd/highway_day.toml", LITE)
    again = parse_odd(odd.describe(), "stored", LITE)
    assert again == ODD(**{**odd.__dict__, "source": "stored"})
    assert isinstance(conditions_model("my.plugin:Backend"), ConditionsModel)
    assert set(KNOBS) >= set(NATURAL_RATES)
    assert StepRecord.from_row(fog_step(3, 5.0, 80.0).to_row()).conditions == Conditions(80.0, 0.0, "dry", "day",
                                                                                          False)
    old = synthetic_step(3).to_row()
    assert "visibility_m" not in old and StepRecord.from_row(old).conditions is None


def test_constant_policy_repeats_its_action_and_checks_it():
    from genesis_rl.adversaries import ConstantPolicy, PolicyContext

    p = ConstantPolicy(PolicyContext(action_dim=5, seed=0, options={"constant_action": [1, 1, 1, 1, 0]}))
    assert p.act(None).tolist() == [1, 1, 1, 1, 0] and p.act(None).tolist() == [1, 1, 1, 1, 0]
    assert ConstantPolicy(PolicyContext(action_dim=3, seed=0, options={"constant_action": [-0.5]})).act(
        None).tolist() == [-0.5] * 3
    assert ConstantPolicy(PolicyContext(action_dim=2, seed=0)).act(None).tolist() == [1.0, 1.0]
    for bad in ([1, 1], [2.0]):
        with pytest.raises(UserInputError, match="--constant-action"):
            ConstantPolicy(PolicyContext(action_dim=5, seed=0, options={"constant_action": bad}))
