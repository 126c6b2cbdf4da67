"""``genesis-rl zoo sweep``: a member's ground truth measured with one knob held at each value, inside its
trigger region and around it; values outside the member's ODD are listed, not driven; resumable; bad input
named (issue 33: "each zoo member's weakness shows in a small sweep")."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from genesis_rl.benchmark.sweep import SweepSpec, in_region, run_sweep, start_weather
from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.zoo import Bound, TriggerRegion, zoo_member


def test_region_membership_and_start_weather_per_value() -> None:
    low_sun = zoo_member("low_sun")
    assert [in_region(low_sun, "sun_altitude_angle", v) for v in (0.0, 14.9, 15.0, -1.0)] == [True, True, False, False]
    assert in_region(low_sun, "fog_density", 50.0) is False  # judged on the whole start: the sun stays at noon
    assert in_region(zoo_member("builtin_highway"), "sun_altitude_angle", 5.0) is None  # a control has no region
    assert start_weather(low_sun, "sun_altitude_angle", 5.0) == "clear_noon,sun_altitude_angle=5"
    # a member that starts elsewhere keeps its start, with the swept knob's own start value replaced
    fog_braking = zoo_member("fog_braking")
    assert start_weather(fog_braking, "lead_decel", 6.0) == "fog_density=26,lead_decel=6"
    assert start_weather(fog_braking, "fog_density", 57.0) == "clear_noon,fog_density=57"
    # a region on a condition is judged on the start weather's conditions: fog 37 gives 95 m of visibility,
    # fog 35 gives 102 m (lite's Koschmieder fog), and a sun sweep leaves the air clear, outside the region
    fog = replace(low_sun, trigger=TriggerRegion((Bound("visibility_m", 50.0, 100.0),)))
    assert [in_region(fog, "fog_density", v) for v in (0.0, 35.0, 37.0, 54.0, 60.0)] == \
        [False, False, True, True, False]
    assert in_region(fog, "sun_altitude_angle", 20.0) is False
    braking = zoo_member("latency_braking")
    assert [in_region(braking, "lead_decel", v) for v in (0.0, 3.9, 4.0, 6.0)] == [False, False, True, True]
    assert in_region(braking, "fog_density", 50.0) is False  # the lead does not brake in a fog sweep
    # a region over two quantities: sweep one, hold the other (--hold); fog 51 gives 60 m of visibility
    both = zoo_member("highway_speed_fog")
    assert [in_region(both, "fog_density", v, (("lead_decel", 6.0),)) for v in (26.0, 51.0)] == [False, True]
    assert in_region(both, "fog_density", 51.0) is False  # without the braking held: fog alone is outside
    assert [in_region(both, "lead_decel", v, (("fog_density", 51.0),)) for v in (3.0, 6.0)] == [False, True]
    assert start_weather(both, "lead_decel", 6.0, (("fog_density", 51.0),)) == "clear_noon,fog_density=51,lead_decel=6"


def test_rows_pool_by_the_start_and_by_what_each_episode_reached() -> None:
    """A region with a flag only a step can tell (glare) gives no verdict on the start; the sweep then pools the
    episodes that reached the region against those that never did. Rows from before 0.19 carry no counts."""
    from genesis_rl.benchmark.sweep import _inside_outside

    rows = [{"inside_odd": True, "in_region": None, "trials": 8, "failed": 5, "reached": 6, "failed_when_reached": 5},
            {"inside_odd": True, "in_region": None, "trials": 8, "failed": 1, "reached": 0, "failed_when_reached": 0},
            {"inside_odd": False, "in_region": None},
            {"inside_odd": True, "in_region": None, "trials": 8, "failed": 2}]  # an old row: no reach counts
    pooled = _inside_outside(rows)
    assert (pooled["reached_region"]["trials"], pooled["reached_region"]["failed"]) == (6, 5)
    assert (pooled["never_reached"]["trials"], pooled["never_reached"]["failed"]) == (10, 1)
    assert (pooled["driven"]["trials"], pooled["driven"]["failed"]) == (24, 8)
    assert pooled["inside_region"]["trials"] == 0
    glare = replace(zoo_member("low_sun"), trigger=TriggerRegion((Bound.flag("sun_glare"),)))
    assert in_region(glare, "sun_altitude_angle", 5.0) is None  # the start cannot say where the camera looks


@pytest.mark.parametrize("kw, message", [
    ({"member": "nope"}, "zoo member 'nope' is unknown"),
    ({"knob": "fog"}, "--knob = 'fog' is unknown; allowed: fog_density"),
    ({"values": ()}, "--values: give at least one value"),
    ({"values": (5.0, 120.0)}, "--values: 120.0 is outside sun_altitude_angle's range [-90, 90]"),
    ({"values": (5.0, 5.0)}, "names a value twice"),
    ({"scenes": 0}, "scenes = 0 must be >= 1"),
    ({"hold": (("fog", 1.0),)}, "--hold: knob 'fog' is unknown"),
    ({"hold": (("fog_density", 120.0),)}, "--hold: 120.0 is outside fog_density's range [0, 100]"),
    ({"hold": (("sun_altitude_angle", 1.0),)}, "names a knob twice or the swept knob 'sun_altitude_angle'"),
])
def test_bad_sweeps_are_refused_naming_the_field(kw, message) -> None:
    base = {"member": "low_sun", "knob": "sun_altitude_angle", "values": (5.0,)}
    with pytest.raises(UserInputError, match=message.replace("[", "\\[").replace("]", "\\]")):
        SweepSpec(**{**base, **kw})


def test_cli_lists_the_zoo_and_refuses_bad_values_with_status_2(tmp_path, capsys) -> None:
    assert main(["zoo", "list"]) == 0
    out = capsys.readouterr().out
    assert "low_sun_highway (weakness, highway, system builtin, ODD highway_day.toml)" in out
    assert "trigger region: 0 <= sun_altitude_angle < 15 deg" in out
    assert main(["zoo", "sweep", "low_sun", "--knob", "sun_altitude_angle", "--values", "5,a",
                 "--out", str(tmp_path / "s")]) == 2
    assert "--values '5,a': give a comma list of numbers" in capsys.readouterr().err
    assert main(["zoo", "sweep", "low_sun", "--knob", "sun_altitude_angle", "--values", "5", "--hold", "fog_density",
                 "--out", str(tmp_path / "s")]) == 2
    assert "--hold 'fog_density': give knob=value pairs, e.g. lead_decel=6" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


@pytest.mark.render
def test_a_sweep_drives_the_values_inside_the_odd_and_resumes_to_the_same_table(tmp_path) -> None:
    spec = SweepSpec(member="low_sun", knob="sun_altitude_angle", values=(-5.0, 5.0, 40.0), scenes=1, steps=30)
    table = run_sweep(spec, tmp_path / "sweep", progress=False)
    rows = table["rows"]
    assert [(r["value"], r["inside_odd"], r["in_region"]) for r in rows] == \
        [(-5.0, False, False), (5.0, True, True), (40.0, True, False)]  # night is outside urban_day: not driven
    assert [r["trials"] for r in rows[1:]] == [1, 1] and "campaign" not in rows[0]
    assert table["inside_region"]["trials"] == table["outside_region"]["trials"] == 1
    assert table["driven"]["trials"] == 2
    assert (tmp_path / "sweep" / "sweep.png").stat().st_size > 10_000
    campaign = json.loads((tmp_path / "sweep" / rows[1]["campaign"] / "campaign.json").read_text())["spec"]
    assert campaign["env"]["start_weather"] == "clear_noon,sun_altitude_angle=5" and campaign["policies"] == ["sunny"]
    again = run_sweep(spec, tmp_path / "sweep", resume=True, progress=False)  # nothing left to drive
    assert again["rows"] == rows
    with pytest.raises(UserInputError, match="--resume: sweep .* was started with"):
        run_sweep(SweepSpec(**{**spec.to_json(), "values": (5.0,)}), tmp_path / "sweep", resume=True, progress=False)
    with pytest.raises(UserInputError, match="exists; pass --resume to continue it or --force"):
        run_sweep(spec, tmp_path / "sweep", progress=False)


@pytest.mark.render
@pytest.mark.parametrize("member, knob, inside, outside, steps, failed", [
    # runs/sweep_low_sun (256 steps): 5 of 8 at 5 deg, at steps 34-105; 0 at 40
    ("low_sun", "sun_altitude_angle", 5.0, 40.0, 110, 5),
    # runs/sweep_low_sun_highway: 2 of 8 at 3 deg, at steps 69 and 77
    ("low_sun_highway", "sun_altitude_angle", 3.0, 45.0, 80, 2),
    # runs/sweep_latency_braking (free-flow traffic, 0.18: the controller no longer slows for phantom bends):
    # 6 of 8 with the lead braking at 6 m/s^2, at steps 87-160; 0 with no braking (0.17: 3 of 8); 0.25 (the
    # ego's lead measured by turned bodies, so the knob may brake a car standing at an angle ahead): 7 of 8;
    # since lead_decel brakes the car in the ego's lane (it had braked a neighbour on bends): 8 of 8
    ("latency_braking", "lead_decel", 6.0, 0.0, 161, 8),
    # runs/sweep_highway_speed_fog (0.19): the lead braking at 6 m/s^2 in fog 56 (54 m): 5 of 8 at steps 82-95,
    # 6 of 8 since lead_decel brakes the ego's own lead; in the member's starting mist (fog 26, 150 m) with the
    # same braking: 0
    ("highway_speed_fog", "fog_density", 56.0, 26.0, 96, 6),
])
def test_each_weakness_fails_inside_its_region_and_not_outside(tmp_path, member, knob, inside, outside, steps,
                                                                 failed) -> None:
    """The member's ground truth in a small sweep: the full sweeps' failures inside, none outside, on the same
    eight scenes (campaign seed 0), cut at the step after their last failure. A region over two quantities
    holds the other inside it (the lead's braking for highway_speed_fog)."""
    hold = (("lead_decel", 6.0),) if member == "highway_speed_fog" else ()
    spec = SweepSpec(member=member, knob=knob, values=(inside, outside), scenes=8, steps=steps, hold=hold)
    table = run_sweep(spec, tmp_path / member, progress=False)
    assert [(r["in_region"], r["failed"]) for r in table["rows"]] == [(True, failed), (False, 0)]
    assert all(s <= steps for s in table["rows"][0]["steps_to_failure"])


@pytest.mark.render
def test_the_glare_blind_detector_fails_in_a_low_sun_ahead_and_not_at_night(tmp_path) -> None:
    """glare_blind's interior band (runs/sweep_glare_blind_alt, the sun held in the west): with the sun 8 deg up
    three of the eight scenes head into it, and one fails by step 101 (at 100; the others at 114 and 199). With
    the sun 5 deg below the horizon (dusk, which the detector's data held) none does. Glare depends on the
    heading, so the start gives no verdict and the rows count the episodes that reached the region."""
    spec = SweepSpec(member="glare_blind", knob="sun_altitude_angle", values=(8.0, -5.0), scenes=8, steps=101,
                     hold=(("sun_azimuth_angle", 270.0),))
    table = run_sweep(spec, tmp_path / "glare", progress=False)
    assert [(r["in_region"], r["reached"], r["failed"], r["failed_when_reached"]) for r in table["rows"]] == \
        [(None, 3, 1, 1), (None, 0, 0, 0)]
    assert table["never_reached"]["failed"] == 0 and table["reached_region"]["trials"] == 3


@pytest.mark.render
def test_the_timing_control_brakes_in_time_where_the_slow_pipeline_does_not(tmp_path) -> None:
    """builtin_braking is latency_braking without the latency: on the same eight free-flow scenes with the lead
    braking at the domain's 6 m/s^2 from the first step, it has no failure in the steps where the slow pipeline
    had six (the test above), so the latency, not the scenes, makes the weakness."""
    spec = SweepSpec(member="builtin_braking", knob="lead_decel", values=(6.0,), scenes=8, steps=161)
    table = run_sweep(spec, tmp_path / "control", progress=False)
    assert [(r["in_region"], r["inside_odd"], r["trials"], r["failed"]) for r in table["rows"]] == \
        [(None, True, 8, 0)]


@pytest.mark.render
@pytest.mark.parametrize(("member", "brake_at_s", "failed"), [
    ("fog_braking", 1.0, 4),  # the lead brakes a second after the fog begins: 4 of 6 (steps 147-183)
    ("fog_braking", 0.0, 0),  # fog and braking together, what a constant schedule does: none
    ("adaptive_braking", 1.0, 0),  # the control, its estimate following the fog within 0.5 s: none
])
def test_fog_braking_fails_when_the_lead_brakes_after_the_fog_thickens(member, brake_at_s, failed) -> None:
    """fog_braking's weakness is one of order, which a held knob cannot show (a sweep holds one): the same six
    free-flow scenes, the fog thickening from 150 m toward 50 m of visibility, the lead braking at 6 m/s^2
    either with it or a second later. Only the slow estimate with the later braking fails; measured with
    more scenes and onsets in docs/zoo.md (fog held at 50 m with braking: 0 of 8)."""
    from genesis_rl.loop.drive import run_episode
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.sut.system.protocol import load_system
    from genesis_rl.sut.zoo.timing import fog_then_brake

    m = zoo_member(member)
    catalog = generate_catalog("highway", 6, 0, traffic=m.traffic)
    weather = fog_then_brake(str(m.env["start_weather"]), brake_at_s, 0.05)
    collided = []
    with LiteBackend() as backend:
        for i in range(6):
            system = load_system(m.system, **m.system_kwargs)
            result = run_episode(backend, catalog.scene(i), system, weather, 190, seed=i, stop_on_collision=True)
            collided.append(any(r.collision.collided for r in result.records))
    assert sum(collided) == failed, collided


@pytest.mark.render
@pytest.mark.parametrize(("altitude", "collided"), [(5.0, True), (45.0, False)])
def test_the_real_photo_detector_loses_a_braking_lead_in_low_sun(altitude, collided) -> None:
    """coco_low_sun's ground truth on its sweep's clearest scene (docs/zoo.md): highway scene 322 of catalog
    seed 0, with its campaign's episode seed. With the sun 5 deg up the COCO detector never finds the braking
    lead in its 76 steps in view and the ego hits it at step 77; with the sun 45 deg up it finds it 15 m ahead
    and stops in time."""
    from genesis_rl.loop.drive import run_episode
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.sut.system.protocol import load_system
    from genesis_rl.world.knobs import parse_weather

    member = zoo_member("coco_low_sun")
    scene = generate_catalog("highway", 1199, 0).scene(322)  # the sweep's catalog: as a 1199-scene campaign's
    weather = parse_weather(f"clear_noon,sun_altitude_angle={altitude:g}")
    with LiteBackend() as backend:
        result = run_episode(backend, scene, load_system(member.system, **member.system_kwargs), lambda k: weather,
                             96 if collided else 50, seed=977508872, stop_on_collision=True)
    hits = [r.step for r in result.records if r.collision.collided]
    assert bool(hits) == collided, hits
    seen = [r.lead.detected for r in result.records[:48] if r.lead.vehicle_id == 1]  # the lead 28 -> 15 m ahead
    assert len(seen) == 48 and (sum(seen) <= 2 if collided else sum(seen) >= 1)
    if collided:
        assert 70 <= hits[0] <= 85
