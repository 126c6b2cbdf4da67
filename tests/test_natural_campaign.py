"""A campaign inside an ODD, end to end: the blind system crashes in clear air on two highway scenes, the
oracle replay avoids both (so perception is to blame), every step is labelled, a random policy pushing the
weather is held inside the domain, and the report leads with distinct in-ODD failures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from genesis_rl.campaigns.campaign_files import read_step_records, steps_path
from genesis_rl.commands.cli import main
from genesis_rl.labels.distinct import failure_key
from genesis_rl.world.knobs import Weather
from genesis_rl.world.odd.conditions import conditions_model
from genesis_rl.world.odd.domain import load_odd

ODD = "configs/odd/highway_day.toml"


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("natural")
    catalog = str(tmp / "highway6.json")
    assert main(["scenes", "--map", "highway", "--count", "6", "--seed", "0", "--out", catalog]) == 0
    out = tmp / "eval"
    # seed 4 picks scenes 3 and 5, where the blind system hits its lead in clear noon
    assert main(["evaluate", "--policies", "sunny,random", "--system", "blind", "--catalog", catalog,
                 "--scenes", "2", "--seed", "4", "--steps", "160", "--odd", ODD, "--dynamics", "paper",
                 "--out", str(out), "--quiet"]) == 0
    return out


def test_clear_air_crashes_of_a_blind_system_are_perception_failures(campaign: Path) -> None:
    rows = [json.loads(p.read_text()) for p in sorted((campaign / "episodes" / "sunny").glob("*.json"))]
    failures = [r["failure"] for r in rows if r["failure"]]
    assert len(failures) == 2
    for f in failures:
        assert f["odd_status"] == "inside" and f["conditions"]["visibility_m"] > 2000
        assert f["evidence"]["visible"] and f["evidence"]["stoppable"]  # seen from afar, room to stop
        assert f["oracle_collides"] is False and f["blame"] == "perception"
        assert f["naturalness"] == 0.0  # sunny holds the weather: the most natural trajectory there is
    summary = json.loads((campaign / "summary.json").read_text())
    natural = summary["policies"]["sunny"]["natural"]
    assert natural["in_odd_collisions"] == 2 and natural["blame"]["perception"] == 2
    assert natural["distinct_in_odd_failures"] == len({failure_key(f) for f in failures})
    assert natural["in_odd_collision_rate"]["rate"] == 1.0
    assert summary["odd"]["name"] == "highway_day"
    assert "speed_for_visibility" in summary["policies"]["sunny"]


def test_random_weather_is_held_inside_the_odd(campaign: Path) -> None:
    odd = load_odd(ODD)
    model = conditions_model("lite")
    statuses = []
    for scene in (3, 5):
        for rec in read_step_records(steps_path(campaign, "random", scene)):
            assert rec.conditions is not None and rec.odd_status is not None
            again = model.conditions(Weather.from_recorded(rec.knobs), None)  # glare needs the heading
            assert (again.visibility_m, again.rain_mm_h, again.road_state, again.light) == (
                rec.conditions.visibility_m, rec.conditions.rain_mm_h, rec.conditions.road_state, rec.conditions.light)
            statuses.append(rec.odd_status)
            assert odd.contains(rec.conditions) or rec.conditions.sun_glare, rec.conditions
    assert statuses.count("boundary") > 0  # it reached a bound and was held there
    rows = [json.loads(p.read_text()) for p in sorted((campaign / "episodes" / "random").glob("*.json"))]
    assert all(r["naturalness"]["ratio_to_held"] < -1e3 for r in rows)  # paper-speed weather is far from natural


def test_report_leads_with_distinct_in_odd_failures(campaign: Path) -> None:
    html = (campaign / "report.html").read_text()
    assert "0. Natural edge cases" in html
    assert "distinct in-ODD failure(s)</b> (2 in-ODD collisions in 2 episodes" in html
    assert "blame: perception 2" in html
    assert html.index("0. Natural edge cases") < html.index("1. Violations by policy")


def test_bad_odd_input_exits_2_naming_the_field(tmp_path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[visibility]\nmin = 150\n')
    assert main(["evaluate", "--policies", "sunny", "--scenes", "1", "--steps", "5", "--odd", str(bad),
                 "--out", str(tmp_path / "x")]) == 2
    assert "visibility: unit is missing; allowed: unit = \"m\"" in capsys.readouterr().err
    assert main(["evaluate", "--policies", "sunny", "--scenes", "1", "--steps", "5", "--odd-label-only",
                 "--out", str(tmp_path / "x")]) == 2
    assert "--odd-label-only needs --odd FILE" in capsys.readouterr().err
    fog = tmp_path / "fog.toml"
    fog.write_text('[visibility]\nmin = 150\nunit = "m"\n')
    cfg = tmp_path / "c.toml"
    cfg.write_text('[env]\nstart_weather = "dense_fog"\n')
    assert main(["evaluate", "--policies", "sunny", "--scenes", "1", "--steps", "5", "--odd", str(fog),
                 "--config", str(cfg), "--out", str(tmp_path / "y")]) == 2
    assert "start weather is outside the ODD" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_a_failure_inside_the_odd_replays_with_its_speed_for_visibility_terms(campaign: Path, tmp_path) -> None:
    record = next((campaign / "records").glob("sunny_*.json"))
    stored = json.loads(record.read_text())
    assert "speed_for_visibility" in [r["name"] for r in stored["rulebook"]]
    assert main(["replay", str(record), "--out", str(tmp_path / "r"), "--no-gif", "--quiet"]) == 0
