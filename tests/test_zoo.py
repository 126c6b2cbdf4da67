"""The zoo's registry and trigger regions: members load by name into a valid env inside their shipped ODD, a
weakness states a region that the records say a step is in or not, a control states none."""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.env.genesis_env import EnvConfig
from genesis_rl.sut.perception.dataset import _typical
from genesis_rl.sut.zoo import EMPTY, ZOO, Bound, TriggerRegion, ZooMember, env_settings, zoo_member
from genesis_rl.sut.zoo.members import ODD_DIR
from genesis_rl.world.knobs import Weather
from genesis_rl.world.odd.conditions import Conditions, conditions_model
from genesis_rl.world.odd.domain import load_odd
from genesis_rl.world.step_record import StepRecord, synthetic_step

ROOT = Path(__file__).resolve().parents[1]


def _sun(altitudes: list[float]) -> list[StepRecord]:
    return [synthetic_step(i + 1, knobs={"sun_altitude_angle": a, "sun_azimuth_angle": 0.0})
            for i, a in enumerate(altitudes)]


def _seen(visibilities: list[float]) -> list[StepRecord]:
    return [replace(synthetic_step(i + 1), conditions=Conditions(v, 0.0, "dry", "day", False), odd_status="inside")
            for i, v in enumerate(visibilities)]


def test_registry_names_kinds_and_regions() -> None:
    assert list(ZOO) == ["low_sun", "low_sun_highway", "latency_braking", "fog_braking", "highway_speed_fog",
                         "coco_low_sun", "glare_blind", "stall_braking", "builtin_highway", "oracle_highway",
                         "builtin_braking", "adaptive_braking"]
    assert {n: m.kind for n, m in ZOO.items()} == {"low_sun": "weakness", "low_sun_highway": "weakness",
                                                    "latency_braking": "weakness", "fog_braking": "weakness",
                                                    "highway_speed_fog": "weakness", "coco_low_sun": "weakness",
                                                    "glare_blind": "weakness", "stall_braking": "weakness",
                                                    "builtin_highway": "control", "oracle_highway": "control",
                                                    "builtin_braking": "control", "adaptive_braking": "control"}
    assert zoo_member("fog_braking").trigger.describe() == "4 <= lead_decel < 8 m/s^2 and 50 <= visibility_m < 100 m"
    # the timing pair differs in the estimate's smoothing alone
    weak, control = zoo_member("fog_braking"), zoo_member("adaptive_braking")
    assert {**weak.system_kwargs, "smoothing_s": 0.5} == dict(control.system_kwargs) and weak.env == control.env
    # the highway profile in fog: fog_braking's domain, start and region, the built-in controller at the same speeds
    fixed = zoo_member("highway_speed_fog")
    assert (fixed.odd, fixed.env, fixed.trigger) == (weak.odd, weak.env, weak.trigger)
    assert fixed.system == "builtin" and fixed.system_kwargs["controller"] == weak.system_kwargs["controller"]
    for name in ("low_sun", "low_sun_highway", "coco_low_sun"):
        assert zoo_member(name).trigger.describe() == "0 <= sun_altitude_angle < 15 deg"
    assert zoo_member("coco_low_sun").system == "coco" and zoo_member("coco_low_sun").odd == "highway_day.toml"
    for name in ("builtin_highway", "oracle_highway"):
        assert zoo_member(name).trigger.empty and zoo_member(name).map == "highway"
    assert (zoo_member("oracle_highway").system, zoo_member("builtin_highway").system) == ("oracle", "builtin")
    # the reactive member: builtin_braking's controller, domain and knobs, behind a stalling camera
    stall, braking = zoo_member("stall_braking"), zoo_member("builtin_braking")
    assert stall.system == "stall" and stall.system_kwargs["controller"] == braking.system_kwargs["controller"]
    assert (stall.odd, stall.traffic, stall.env["knobs"]) == (braking.odd, braking.traffic, braking.env["knobs"])
    assert stall.trigger.describe() == "4 <= lead_decel < 8 m/s^2 and stale_frames"


def test_unknown_member_is_refused_naming_the_members() -> None:
    with pytest.raises(UserInputError, match="zoo member 'nope' is unknown; allowed: low_sun, low_sun_highway, "
                                             "latency_braking, fog_braking, highway_speed_fog, coco_low_sun, "
                                             "glare_blind, stall_braking, builtin_highway, oracle_highway, "
                                             "builtin_braking, adaptive_braking"):
        zoo_member("nope")


@pytest.mark.parametrize("name", list(ZOO))
def test_env_settings_make_a_valid_env_inside_the_members_odd(name: str) -> None:
    member = ZOO[name]
    settings = env_settings(member)
    cfg = EnvConfig(**settings)  # checks every field, loads the ODD, checks the start weather lies inside it
    assert (cfg.map, cfg.system, cfg.dynamics) == (member.map, member.system, "natural")
    assert Path(cfg.odd or "").parent == ODD_DIR and cfg.load_odd().name == load_odd(member.odd_path).name
    settings["system_kwargs"]["x"] = 1  # a fresh dict: the registry's member is untouched
    assert "x" not in env_settings(member)["system_kwargs"]


def test_every_shipped_odd_loads_and_is_package_data() -> None:
    model = conditions_model("lite")
    shipped = sorted(p.name for p in ODD_DIR.glob("*.toml"))
    assert shipped == ["highway_braking.toml", "highway_day.toml", "highway_fog_braking.toml", "highway_high_sun.toml",
                       "urban_any_hour.toml", "urban_day.toml"]
    assert {m.odd for m in ZOO.values()} == set(shipped)
    for name in shipped:
        load_odd(ODD_DIR / name, model)
    # the highway weakness's domain is the one docs/results/07-reactive-adversary-in-odd.md measured in; the
    # control's is it with the sun at least 15 deg up, and nothing else changed
    ours, theirs = load_odd(ODD_DIR / "highway_day.toml").describe(), load_odd(ROOT / "configs/odd/highway_day.toml")
    assert ours == theirs.describe()
    high = load_odd(ODD_DIR / "highway_high_sun.toml").describe()
    assert high.pop("sun_altitude") == {"min": 15.0, "max": 90.0, "unit": "deg"}
    assert {k: v for k, v in high.items() if k not in ("name", "description")} == \
        {k: v for k, v in ours.items() if k not in ("name", "description")}
    braking = load_odd(ODD_DIR / "highway_braking.toml").describe()  # the timing members': high sun, stated traffic
    assert braking.pop("traffic") == {"max_lead_decel": 6.0, "min_cut_in_ttc": 1.64}
    assert {k: v for k, v in braking.items() if k not in ("name", "description")} == \
        {k: v for k, v in load_odd(ODD_DIR / "highway_high_sun.toml").describe().items()
         if k not in ("name", "description")}
    fog = load_odd(ODD_DIR / "highway_fog_braking.toml").describe()  # the fog pair's: highway_braking down to 50 m
    assert fog.pop("visibility")["min"] == 50.0
    assert {k: v for k, v in fog.items() if k not in ("name", "description")} == \
        {k: v for k, v in load_odd(ODD_DIR / "highway_braking.toml").describe().items()
         if k not in ("name", "description", "visibility")}
    # the glare-blind member's domain: urban_day at every hour (twilight and night added), nothing else changed
    any_hour = load_odd(ODD_DIR / "urban_any_hour.toml").describe()
    assert any_hour.pop("light") == {"allowed": ["day", "twilight", "night"]}
    day = load_odd(ODD_DIR / "urban_day.toml").describe()
    assert {k: v for k, v in any_hour.items() if k not in ("name", "description")} == \
        {k: v for k, v in day.items() if k not in ("name", "description", "light")}
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["genesis_rl"]
    assert "sut/zoo/odd/*.toml" in globs and "sut/zoo/weights/*" in globs


def test_the_glare_blind_member_loads_its_shipped_detector_and_states_an_interior_band() -> None:
    """Its weights ship with the package (reproduced by ``detector train --condition sun_behind``); its region is
    a band of sun altitude that the domain's own bounds (night below, noon above) do not touch."""
    from genesis_rl.sut.perception.dataset import SUN_BEHIND_HALF_ANGLE_DEG, sample_weather
    from genesis_rl.sut.system.protocol import load_system
    from genesis_rl.sut.zoo.members import GLARE_BLIND_WEIGHTS

    member = zoo_member("glare_blind")
    system = load_system(member.system, **member.system_kwargs)
    assert system.detector.weights_path == GLARE_BLIND_WEIGHTS and GLARE_BLIND_WEIGHTS.stat().st_size > 100_000
    meta = json.loads(GLARE_BLIND_WEIGHTS.with_suffix(".json").read_text())
    assert meta["train_config"]["condition"] == "sun_behind"
    assert member.trigger.describe() == "sun_glare and 0 <= sun_altitude_angle < 15 deg"
    odd = load_odd(member.odd_path)
    rng = np.random.default_rng(0)
    for yaw in (0.0, 1.0, 3.0):  # the training mix never puts the sun within 60 deg of the camera's heading
        for _ in range(200):
            w = sample_weather("sun_behind", rng, yaw)
            off = (w["sun_azimuth_angle"] - np.degrees(yaw) + 180.0) % 360.0 - 180.0
            assert abs(off) >= SUN_BEHIND_HALF_ANGLE_DEG - 1e-9 and -30.0 <= w["sun_altitude_angle"] <= 90.0
    model = conditions_model("lite")
    for altitude in (-20.0, -5.0, 8.0, 60.0):  # night, dusk, the band and noon are all inside the domain
        w = Weather.preset("clear_noon").replace(sun_altitude_angle=altitude)
        assert odd.contains(model.conditions(w, None), w)


def test_low_sun_region_is_inside_the_day_odd_and_outside_the_detectors_training_data() -> None:
    odd, model = load_odd(ODD_DIR / "urban_day.toml"), conditions_model("lite")
    for altitude, inside in ((0.0, True), (5.0, True), (14.9, True), (-1.0, False)):  # day: the sun >= 0 deg
        c = model.conditions(Weather.default().replace(sun_altitude_angle=altitude), None)
        assert odd.contains(c) is inside, altitude
    rng = np.random.default_rng(0)
    drawn = [_typical(rng, 0.0)["sun_altitude_angle"] for _ in range(2000)]
    low = zoo_member("low_sun").trigger.bounds[0]
    assert min(drawn) >= low.high  # the detector never saw a sun in the region
    assert low.low == 0.0 and low.high == 15.0


def test_the_controls_domain_excludes_the_low_sun_the_weakness_domain_allows() -> None:
    """builtin_highway is a control because its ODD leaves out the built-in detector's blind spot, which
    low_sun_highway's domain allows: the same sun inside one and outside the other, labelled and kept so."""
    from genesis_rl.env import GenesisEnv

    model = conditions_model("lite")
    weak, control = load_odd(ODD_DIR / "highway_day.toml"), load_odd(ODD_DIR / "highway_high_sun.toml")
    for altitude, in_weak, in_control in ((5.0, True, False), (14.9, True, False), (15.0, True, True),
                                          (60.0, True, True), (-1.0, False, False)):
        w = Weather.default().replace(sun_altitude_angle=altitude)
        assert (weak.contains(model.conditions(w, None), w), control.contains(model.conditions(w, None), w)) == \
            (in_weak, in_control), altitude
    low = Weather.default().replace(sun_altitude_angle=5.0)
    assert control.violations(model.conditions(low, None), low) == ["sun_altitude 5 deg not in [15, 90]"]
    env = GenesisEnv(**env_settings(zoo_member("builtin_highway")))  # natural starts stay in the control's domain
    try:
        assert env.held_knobs == ("sun_altitude_angle", "sun_azimuth_angle")
        rng = np.random.default_rng(0)
        assert min(env.natural_start(rng)["sun_altitude_angle"] for _ in range(50)) >= 15.0
        assert env.start_from([0.0, 0.5])["sun_altitude_angle"] == pytest.approx(15.0, abs=0.2)  # the corner
    finally:
        env.close()


def test_the_timing_pair_differs_in_the_latency_alone_and_braking_is_its_trigger() -> None:
    """latency_braking and its control builtin_braking: the same controller profile, domain, knobs and free-flowing
    traffic; the weakness adds the pipeline's latency, and its region is the lead's hard braking inside the
    domain (4 m/s^2 up to the domain's 6), which only an actor knob brings (free flow: no lead stops on its own)."""
    from genesis_rl.sut.zoo.members import HIGHWAY_PROFILE, PIPELINE_LATENCY_S

    weak, control = zoo_member("latency_braking"), zoo_member("builtin_braking")
    assert (weak.system, control.system) == ("latency", "builtin")
    assert weak.system_kwargs == {"latency_s": PIPELINE_LATENCY_S, "controller": dict(HIGHWAY_PROFILE)}
    assert control.system_kwargs == {"controller": dict(HIGHWAY_PROFILE)}
    assert (weak.odd, weak.map, weak.traffic, dict(weak.env)) == \
        (control.odd, control.map, control.traffic, dict(control.env))
    assert weak.traffic == "free_flow" and "lead_decel" in weak.env["knobs"]
    assert weak.trigger.describe() == "4 <= lead_decel < 8 m/s^2"
    odd = load_odd(weak.odd_path)
    assert odd.traffic.max_lead_decel == 6.0 and odd.sun_altitude is not None and odd.sun_altitude[0] == 15.0
    assert zoo_member("low_sun").traffic == "mixed"  # the weather members keep the paper's traffic
    with pytest.raises(UserInputError, match="traffic = 'jam'; allowed: mixed, free_flow"):
        replace(weak, traffic="jam")


def test_reached_is_the_first_step_inside_a_half_open_region() -> None:
    region = zoo_member("low_sun").trigger
    assert region.reached(_sun([40.0, 15.0, 14.9, 5.0])) == 2  # 15 deg is outside: the bound is [0, 15)
    assert region.reached(_sun([40.0, 20.0, -3.0, 15.0])) is None  # below the horizon is not the region either
    assert region.reached([]) is None
    fog = TriggerRegion((Bound("visibility_m", high=150.0),))
    assert fog.describe() == "visibility_m < 150 m"
    assert fog.reached(_seen([3000.0, 400.0, 150.0, 120.0, 80.0])) == 3
    both = TriggerRegion((Bound("visibility_m", high=150.0), Bound("rain_mm_h", 2.5)))
    assert both.describe() == "visibility_m < 150 m and rain_mm_h >= 2.5 mm/h"
    assert both.reached(_seen([100.0])) is None  # no rain: a conjunction needs every bound


def test_a_flag_condition_bounds_a_region_by_what_the_camera_sees() -> None:
    """Glare depends on where the camera looks, so a region names the step's ``sun_glare`` flag: it holds while
    the flag is set, together with the sun's altitude band."""
    def step(i: int, altitude: float, glare: bool) -> StepRecord:
        return replace(synthetic_step(i, knobs={"sun_altitude_angle": altitude}),
                       conditions=Conditions(3000.0, 0.0, "dry", "day", glare), odd_status="inside")

    glare = TriggerRegion((Bound.flag("sun_glare"), Bound("sun_altitude_angle", 0.0, 12.0)))
    assert glare.describe() == "sun_glare and 0 <= sun_altitude_angle < 12 deg"
    assert glare.reached([step(1, 8.0, False), step(2, 20.0, True), step(3, 8.0, True)]) == 2
    assert glare.reached([step(1, 8.0, False), step(2, 12.0, True)]) is None  # behind, then too high
    assert Bound.flag("sun_glare", is_set=False).describe() == "no sun_glare"
    assert Bound.flag("sun_glare", is_set=False).holds(step(1, 8.0, False))


def test_empty_region_is_never_reached() -> None:
    assert EMPTY.empty and EMPTY.reached(_sun([5.0, 0.0])) is None
    assert EMPTY.describe().startswith("empty")


def test_an_actor_knob_missing_from_old_records_sits_at_its_default() -> None:
    braking = TriggerRegion((Bound("lead_decel", 3.0),))
    assert braking.describe() == "lead_decel >= 3 m/s^2"
    assert braking.reached(_sun([50.0, 50.0])) is None  # lead_decel 0 (its default) in records without it
    recs = [synthetic_step(1, knobs={"lead_decel": 0.0}), synthetic_step(2, knobs={"lead_decel": 4.0})]
    assert braking.reached(recs) == 1


def test_bad_bounds_and_members_are_refused_naming_the_field() -> None:
    with pytest.raises(UserInputError, match="quantity = 'sun' is unknown; allowed: a knob .*sun_altitude_angle"):
        Bound("sun", 0.0, 1.0)
    with pytest.raises(UserInputError, match="low 15 must be below high 15"):
        Bound("sun_altitude_angle", 15.0, 15.0)
    with pytest.raises(UserInputError, match="low nan"):
        Bound("sun_altitude_angle", math.nan, 1.0)
    with pytest.raises(UserInputError, match="carries no conditions: run the campaign with an ODD"):
        TriggerRegion((Bound("visibility_m", high=150.0),)).reached(_sun([5.0]))
    base = zoo_member("builtin_highway")
    with pytest.raises(UserInputError, match="kind = 'weak'; allowed: weakness, control"):
        replace(base, kind="weak")
    with pytest.raises(UserInputError, match="map = 'town10'; allowed: urban, highway"):
        replace(base, map="town10")
    with pytest.raises(UserInputError, match="a control's trigger region must be empty"):
        replace(base, trigger=zoo_member("low_sun").trigger)
    with pytest.raises(UserInputError, match="a weakness's trigger region must be non-empty"):
        replace(base, kind="weakness")
    with pytest.raises(UserInputError, match=r"env key\(s\) \['system'\] are the member's own fields"):
        ZooMember(name="x", kind="control", summary="", system="builtin", odd="highway_day.toml", map="highway",
                  trigger=EMPTY, env={"system": "oracle"})


def test_a_run_naming_the_shipped_weights_from_the_repository_matches_the_member(monkeypatch):
    """configs/zoo_glare_blind_sac.toml names the weights relative to the repository; the member names them by
    absolute path: one file, so the benchmark must not refuse the agent over the spelling."""
    from genesis_rl.benchmark.matrix import _same_weights_spelling

    monkeypatch.chdir(ODD_DIR.parents[3])  # the repository: genesis_rl/sut/zoo/odd
    member = zoo_member("glare_blind")
    relative = {"weights": "genesis_rl/sut/zoo/weights/glare_blind_detector.pt"}
    assert relative != dict(member.system_kwargs)
    assert _same_weights_spelling(relative) == _same_weights_spelling(dict(member.system_kwargs))
    assert _same_weights_spelling({"weights": "other.pt"}) != _same_weights_spelling(dict(member.system_kwargs))
