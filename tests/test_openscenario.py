"""OpenSCENARIO export (issue 37): the knob mapping, the polyline, ASAM's schemas, the read-back and the lite
replay of an exported failure."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("scenariogeneration")

from genesis_rl.commands.cli import main  # noqa: E402
from genesis_rl.exports.openscenario.environment import (  # noqa: E402
    MINOR_VERSIONS,
    environment_of,
    expressed_knobs,
    knobs_from_environment,
)
from genesis_rl.exports.openscenario.reader import read_scenario  # noqa: E402
from genesis_rl.exports.openscenario.schema import validate, validate_opendrive, validate_scenario  # noqa: E402
from genesis_rl.exports.openscenario.trace import EpisodeTrace, VehicleTrack  # noqa: E402
from genesis_rl.exports.openscenario.writer import polyline_vertices, rear_axle, write_scenario  # noqa: E402
from genesis_rl.world.knobs import KNOBS, Weather  # noqa: E402

DT = 0.05


# -- the knob mapping -----------------------------------------------------------------------------------
@pytest.mark.parametrize("minor", MINOR_VERSIONS)
def test_every_expressed_knob_comes_back_exactly(minor: int) -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        knobs = {k: float(rng.uniform(KNOBS[k].low, KNOBS[k].high)) for k in KNOBS}
        back = knobs_from_environment(environment_of(knobs, minor), minor)
        assert set(back) == set(expressed_knobs(minor))
        for name, value in back.items():
            diff = abs(value - knobs[name])
            if KNOBS[name].wraps:
                diff = min(diff, KNOBS[name].span - diff)
            assert diff < 1e-9, (name, knobs[name], value)


def test_the_mapping_by_hand() -> None:
    w = Weather.from_partial({"fog_density": 0.0, "precipitation": 50.0, "cloudiness": 30.0,
                              "precipitation_deposits": 100.0, "sun_altitude_angle": 30.0,
                              "sun_azimuth_angle": 90.0, "wind_intensity": 50.0}).as_dict()
    v10 = environment_of(w, 0)
    assert v10.fog_visual_range == pytest.approx(3000.0)  # lite's clear-air haze
    assert v10.precipitation_type == "rain"
    assert v10.precipitation_intensity == pytest.approx(0.5)  # ScenarioRunner: precipitation = 100 x
    assert v10.sun_intensity == pytest.approx(0.7)  # ScenarioRunner: cloudiness = 100 - 100 x
    assert v10.sun_elevation == pytest.approx(math.pi / 6) and v10.sun_azimuth == pytest.approx(math.pi / 2)
    assert v10.friction_scale_factor == pytest.approx(0.6)
    assert v10.cloud_state == "rainy" and v10.wetness is None and v10.wind_speed is None
    v12 = environment_of(w, 2)
    assert v12.precipitation_intensity == pytest.approx(7.6)  # mm/h from 1.1 on (odd.conditions' table)
    assert v12.cloud_state == "twoOktas" and v12.wetness == "lowFlooded" and v12.wind_speed == pytest.approx(10.0)
    fog = environment_of({**w, "fog_density": 60.0}, 0)
    assert fog.fog_visual_range == pytest.approx(45.0)


# -- the polyline ---------------------------------------------------------------------------------------
def test_polyline_keeps_the_fewest_vertices_within_tolerance() -> None:
    t = np.arange(200) * DT
    cruise = np.column_stack([10.0 * t, np.zeros_like(t), np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)])
    assert polyline_vertices(t, cruise, np.full(5, 0.002)) == [0, 199]
    speed = np.maximum(20.0 - 6.0 * np.maximum(t - 3.0, 0.0), 0.0)  # CCRb: brakes at 6 m/s^2 from 3 s
    x = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * DT)])
    path = np.column_stack([x, np.zeros_like(t), np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)])
    keep = polyline_vertices(t, path, np.full(5, 0.002))
    assert 10 < len(keep) < 200 and keep[0] == 0 and keep[-1] == 199
    assert np.max(np.abs(np.interp(t, t[keep], x[keep]) - x)) <= 0.002


# -- a crafted episode: a lead braking in thickening fog --------------------------------------------------
def _track(i: int, make: str, x0: float, speed: np.ndarray, lane: int = 0) -> VehicleTrack:
    x = x0 + np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * DT)])
    n = len(speed)
    return VehicleTrack(i, "ego" if i == 0 else "npc", make, "white", 4.6, 1.85, 1.45, lane, float(x0), lane,
                        x, np.full(n, -1.75), np.zeros(n), np.zeros(n), np.zeros(n), speed)


def _trace(steps: int = 60) -> EpisodeTrace:
    t = np.arange(steps + 1) * DT
    lead = np.maximum(15.0 - 6.0 * np.maximum(t - 1.0, 0.0), 0.0)
    names = tuple(KNOBS)
    rows = []
    for k in range(steps):
        w = Weather.from_partial({"fog_density": min(100.0, 2.0 * k), "wetness": 40.0,
                                  "lead_decel": 6.0 if k >= 20 else 0.0})
        rows.append([w[n] for n in names])
    return EpisodeTrace(
        name="crafted", map="highway", dt=DT, times=t,
        vehicles=(_track(0, "sedan", 0.0, np.full(steps + 1, 15.0)), _track(1, "van", 30.0, lead),
                  _track(2, "bus", 60.0, np.full(steps + 1, 12.0))),
        knob_names=names, schedule=np.array(rows), start_weather=Weather.default().as_dict(), signal_offset=3.5,
        scene_seed=7, episode_seed=11, system={"spec": "builtin", "kwargs": {}}, rulebook=[{"name": "collision"}],
        camera=(320, 240), policy="agent", scene_index=5, violations={"collision": 1.0}, first_collision_step=None,
        collision_with=None)


@pytest.fixture(scope="module")
def crafted(tmp_path_factory) -> tuple[EpisodeTrace, dict[int, Path]]:
    trace = _trace()
    folder = tmp_path_factory.mktemp("osc")
    files = {}
    for minor in MINOR_VERSIONS:
        files[minor] = folder / f"crafted_1_{minor}.xosc"
        write_scenario(trace, files[minor], "highway.xodr", minor)
    return trace, files


@pytest.mark.parametrize("minor", MINOR_VERSIONS)
def test_every_version_validates_against_asams_schema(crafted, minor: int) -> None:
    _, files = crafted
    result = validate_scenario(files[minor])
    assert result.schema.startswith(f"OpenSCENARIO_1_{minor}") and result.valid, result.errors[:3]


def test_the_schema_check_can_fail(crafted, tmp_path) -> None:
    """A Fog without its visual range, and a vehicle without its category: both must be refused."""
    _, files = crafted
    text = files[0].read_text()
    broken = tmp_path / "broken.xosc"
    broken.write_text(text.replace('visualRange="', 'range="', 1))
    assert not validate_scenario(broken).valid
    broken.write_text(text.replace(' vehicleCategory="car"', "", 1))
    errors = validate_scenario(broken).errors
    assert errors and "vehicleCategory" in errors[0]


def test_read_back_gives_the_same_actors_paths_and_weather(crafted) -> None:
    trace, files = crafted
    for minor, path in files.items():
        parsed = read_scenario(path)
        assert parsed.minor == minor and parsed.stop_after_s == pytest.approx(trace.duration)
        assert [v.name for v in parsed.vehicles] == ["hero", "vehicle_1", "vehicle_2"]
        assert parsed.vehicles[0].is_ego and parsed.vehicles[0].properties["genesis.make"] == "sedan"
        assert parsed.parameters["GenesisSceneSeed"] == "7" and parsed.parameters["GenesisEpisodeSeed"] == "11"
        for track, v in zip(trace.vehicles, parsed.vehicles, strict=True):
            xr, yr = rear_axle(track)
            assert v.start[:2] == pytest.approx([xr[0], yr[0]], abs=1e-4)
            assert v.start_speed == pytest.approx(track.speed[0])
            assert v.wheelbase == pytest.approx({"sedan": 2.8, "van": 3.3, "bus": 6.0}[track.make])
            assert np.max(np.abs(np.interp(trace.times, v.times, v.poses[:, 0]) - xr)) < 0.0021
        # the braking lead's path: 15 m/s for 1 s, then 2 s at 6 m/s^2: 30 + 15 + (30 - 12) m at 3 s
        lead = parsed.vehicle("vehicle_1")
        assert lead.poses[-1, 0] + 0.5 * 3.3 == pytest.approx(30.0 + 15.0 + 18.0, abs=0.003)
        steps = {w.name: w for w in parsed.weather}
        # the start's other knobs, then an event per step whose knobs changed: the fog stops rising at step 50
        assert len(steps) == 1 + 51 and "weather_step_51" not in steps
        for k in (0, 10, 50):
            back = knobs_from_environment(steps[f"weather_step_{k}"].environment, minor)
            assert back["fog_density"] == pytest.approx(min(100.0, 2.0 * k), abs=1e-6)
            assert steps[f"weather_step_{k}"].after_s == pytest.approx((k - 0.5) * DT)
            assert steps[f"weather_step_{k}"].other_knobs["wetness"] == 40.0


def test_weather_events_are_written_only_when_the_knobs_change(tmp_path) -> None:
    trace = _trace(30)
    still = EpisodeTrace(**{**trace.__dict__, "schedule": np.repeat(trace.schedule[:1], 30, axis=0)})
    write_scenario(still, tmp_path / "still.xosc", "highway.xodr", 0)
    events = [e.get("name") for e in ET.parse(tmp_path / "still.xosc").iter("Event")]
    assert [e for e in events if e.startswith("weather_step_")] == ["weather_step_0"]


def test_lite_weather_from_a_parsed_file_follows_the_events(crafted) -> None:
    from genesis_rl.exports.openscenario.lite_replay import scenario_weathers

    trace, files = crafted
    start, weathers, sources = scenario_weathers(read_scenario(files[0]), DT, len(trace.schedule))
    assert start["fog_density"] == 0.0
    fog = trace.knob_names.index("fog_density")
    # row k of the schedule before step k + 1, also after the last event (the fog holds at 100 from step 50)
    assert [w["fog_density"] for w in weathers] == pytest.approx(list(trace.schedule[:, fog]), abs=1e-6)
    assert weathers[40]["wetness"] == 40.0 and weathers[40]["lead_decel"] == 0.0  # actors move by their paths
    assert sources["fog_density"] == "standard" and sources["wetness"] == "genesis"


def test_scripted_vehicles_are_where_the_file_puts_them_after_every_step(crafted) -> None:
    """Row k of a script is the pose after step k + 1 (the trace's sample k + 1), box centre, with its speed."""
    from genesis_rl.exports.openscenario.lite_replay import _script

    trace, files = crafted
    lead = read_scenario(files[0]).vehicle("vehicle_1")
    script = _script(lead, DT, len(trace.schedule))
    track = trace.vehicles[1]
    assert np.max(np.abs(script.x - track.x[1:])) < 0.003 and np.max(np.abs(script.y - track.y[1:])) < 0.003
    assert script.speed == pytest.approx(track.speed[1:], abs=0.16)  # means of the chords around each sample
    assert script.speed[-1] == pytest.approx(track.speed[-1], abs=0.16)  # the last step too
    assert not script.braking[:15].any() and script.braking[25:].all()  # lit from 1 s, when the lead brakes


def test_a_file_of_another_step_length_is_refused(crafted, tmp_path) -> None:
    from genesis_rl.core.errors import UserInputError
    from genesis_rl.exports.openscenario.lite_replay import scene_of

    _, files = crafted
    path = tmp_path / "slow.xosc"
    path.write_text(files[0].read_text().replace('name="GenesisStepSeconds" parameterType="double" value="0.05"',
                                                 'name="GenesisStepSeconds" parameterType="double" value="0.1"'))
    with pytest.raises(UserInputError, match="GenesisStepSeconds = 0.1; allowed: 0.05"):
        scene_of(read_scenario(path))


@pytest.mark.parametrize("name", ["urban", "highway"])
def test_the_map_export_validates_against_opendrive_1_7(tmp_path, name: str) -> None:
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive

    path = tmp_path / f"{name}.xodr"
    path.write_text(to_opendrive(load_map(name)))
    result = validate_opendrive(path)
    assert result.valid, result.errors[:3]  # before issue 37: every traffic light failed on unit=""
    assert validate(path, "opendrive_17_core.xsd").schema == "opendrive_17_core.xsd"


# -- a campaign's failure, exported and driven again from the file ----------------------------------------
@pytest.fixture(scope="module")
def failing_campaign(tmp_path_factory) -> Path:
    from genesis_rl.campaigns.campaign import CampaignSpec, run_campaign
    from genesis_rl.sim.lite.scenes import generate_catalog

    catalog = tmp_path_factory.mktemp("cat") / "highway.json"
    generate_catalog("highway", 12, 0).save(catalog)
    folder = tmp_path_factory.mktemp("camp") / "eval"
    # the blind system never sees a vehicle: scene 5 (seed 1) ends in a collision at step 49
    spec = CampaignSpec(policies=("random",), catalog=str(catalog), scenes=3, seed=1, steps=70,
                        env={"system": "blind"})
    run_campaign(spec, folder, progress=False)
    return folder


def test_export_validates_reads_back_and_reproduces_the_collision(failing_campaign: Path, tmp_path, capsys) -> None:
    out = tmp_path / "osc"
    assert main(["export", str(failing_campaign), "--format", "openscenario", "--out", str(out), "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    index = json.loads((out / "scenarios.json").read_text())
    assert result["scenarios"] == len(index["scenarios"]) >= 1
    entry = index["scenarios"][0]
    assert entry["record_replayed_exactly"] and entry["schema"]["valid"] and entry["read_back"]["ok"]
    assert entry["first_collision_step"] is not None
    replay = entry["replay"]
    assert replay["reproduced"], replay
    assert replay["from_scenario"]["first_collision_step"] == pytest.approx(entry["first_collision_step"], abs=1)
    assert "fog_density" in replay["knobs_from_standard"]
    assert index["maps"]["highway"]["valid"] and (out / "scenarios" / "highway.xodr").is_file()
    assert (out / entry["scenario"]).is_file()
    # the second time without --force: refused, nothing lost
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert main(["export", str(failing_campaign), "--format", "openscenario", "--out", str(out), "--quiet"]) == 2
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # the read-back check can fail: a file missing one weather event gives lite the step before's weather
    from genesis_rl.campaigns.records import load_record
    from genesis_rl.exports.openscenario.export import roundtrip_errors
    from genesis_rl.exports.openscenario.trace import trace_record

    record = Path(entry["record"])
    trace, _ = trace_record(load_record(record), record.stem)
    assert roundtrip_errors(trace, read_scenario(out / entry["scenario"]))["ok"]
    root = ET.parse(out / entry["scenario"]).getroot()
    rows = trace.schedule
    changing = [k for k in range(1, len(rows)) if not np.array_equal(rows[k], rows[k - 1])]
    for parent in root.iter("Maneuver"):
        for event in list(parent):
            if event.get("name") == f"weather_step_{changing[0]}":
                parent.remove(event)
    ET.ElementTree(root).write(tmp_path / "gap.xosc")
    errors = roundtrip_errors(trace, read_scenario(tmp_path / "gap.xosc"))
    assert not errors["ok"] and errors["knob_share"] > 1e-7


def test_a_moved_vehicle_changes_the_replay(failing_campaign: Path, tmp_path) -> None:
    """The lite replay really follows the file: a file whose struck vehicle is moved out of the ego's lane
    no longer collides there."""
    from genesis_rl.exports.openscenario.export import export_scenarios
    from genesis_rl.exports.openscenario.lite_replay import drive_scenario

    index = export_scenarios(failing_campaign, tmp_path, check=False, progress=False)
    entry = index["scenarios"][0]
    path = tmp_path / entry["scenario"]
    root = ET.parse(path).getroot()
    struck = entry["collision_with"]
    moved = 0
    for group in root.iter("ManeuverGroup"):
        if [a.get("entityRef") for a in group.iter("EntityRef")] == [struck]:
            for world in group.iter("WorldPosition"):
                world.set("y", str(float(world.get("y")) + 40.0))
                moved += 1
    assert moved > 1
    ET.ElementTree(root).write(path)
    drive = drive_scenario(read_scenario(path))
    assert drive.first_collision_step is None or drive.collision_with != int(struck.split("_")[1])


@pytest.mark.parametrize(("argv", "message"), [
    (["--format", "openscenario", "--osc-version", "2.0"], "--osc-version '2.0' is unknown; allowed: 1.0, 1.1"),
    (["--format", "xosc"], "--format 'xosc' is unknown; allowed: yolo, coco, openscenario"),
    (["--format", "openscenario", "--policies", "random"], "--policies and --scenarios go with --format yolo"),
])
def test_bad_export_input_exits_2(failing_campaign: Path, tmp_path, capsys, argv, message) -> None:
    assert main(["export", str(failing_campaign), "--out", str(tmp_path / "x"), *argv]) == 2
    assert message in capsys.readouterr().err


def test_dataset_export_carries_the_scenarios_and_the_report_links_them(failing_campaign: Path, tmp_path,
                                                                        capsys) -> None:
    out = tmp_path / "yolo"
    assert main(["export", str(failing_campaign), "--format", "yolo", "--scenarios", "--no-check", "--out", str(out),
                 "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["scenarios"] >= 1 and "not checked" in result["scenarios_summary"]
    metadata = [json.loads(line) for line in (out / "metadata.jsonl").read_text().splitlines()]
    linked = {m["scenario"] for m in metadata if "scenario" in m}
    assert linked and all((out / s).is_file() for s in linked)  # each failure's frames beside its scenario
    report = tmp_path / "report.html"
    assert main(["report", str(failing_campaign), "--out", str(report), "--scenarios", str(out)]) == 0
    page = report.read_text()
    name = Path(sorted(linked)[0]).name
    assert f">{name}</a>" in page and "href='yolo/scenarios/" in page
    plain = tmp_path / "plain.html"
    assert main(["report", str(failing_campaign), "--out", str(plain)]) == 0
    assert "--format openscenario --out scenarios_" in plain.read_text()  # no export: the command that makes one
