import json
import subprocess
import sys

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.backends import catalog_from_json, load_catalog
from genesis_rl.sim.lite.maps import load_map
from genesis_rl.sim.lite.scenes import generate_catalog
from genesis_rl.world.scenes.vehicles import MAKES


@pytest.mark.parametrize("map_name", ["urban", "highway"])
def test_scene_composition(map_name):
    cat = generate_catalog(map_name, 10, 0)
    m = load_map(map_name)
    makes = set()
    for sc in cat.scenes:
        roles = [v.role for v in sc.vehicles]
        assert len(sc.vehicles) == 30 and roles[:3] == ["ego", "lead", "neighbour"]
        ego, lead, nb = sc.vehicles[:3]
        assert lead.lane == ego.lane and lead.s > ego.s
        assert nb.lane == m.lanes[ego.lane].right
        xy = np.array([[v.x, v.y] for v in sc.vehicles])
        d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(30) * 99
        assert d.min() > 1.5  # no overlaps
        assert np.hypot(*(xy - xy[0]).T).max() < 95
        makes |= {v.make for v in sc.vehicles}
    assert makes >= {"sedan", "suv", "van", "truck", "bus"}


def test_same_seed_same_catalog_other_seed_differs():
    a = generate_catalog("highway", 5, 11).to_json()
    assert a == generate_catalog("highway", 5, 11).to_json()
    assert a != generate_catalog("highway", 5, 12).to_json()


def test_roundtrip_and_bad_catalogs(tmp_path):
    cat = generate_catalog("urban", 2, 0)
    path = tmp_path / "c.json"
    cat.save(path)
    assert load_catalog(path).to_json() == cat.to_json()
    data = json.loads(path.read_text())
    data["version"] = 99
    with pytest.raises(UserInputError, match="version"):
        catalog_from_json(data)
    data = json.loads(path.read_text())
    data["scenes"][1]["vehicles"][4]["make"] = "tank"
    with pytest.raises(UserInputError, match=r"scenes\[1\]\.vehicles\[4\]\.make.*allowed: " + ", ".join(MAKES)):
        catalog_from_json(data)
    path.write_text("{ not json")
    with pytest.raises(UserInputError, match="not valid JSON"):
        load_catalog(path)


def test_cli_scenes_refuses_overwrite_and_bad_map(tmp_path):
    out = tmp_path / "s.json"
    cmd = [sys.executable, "-m", "genesis_rl", "scenes", "--map", "highway", "--count", "3",
           "--out", str(out), "--quiet"]
    assert subprocess.run(cmd, capture_output=True).returncode == 0
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 2 and "--force" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(cmd[:5] + ["mars"] + cmd[6:] + ["--force"], capture_output=True, text=True)
    assert r.returncode == 2 and "allowed: urban, highway" in r.stderr


def _tampered(path_data: dict, edit) -> dict:  # noqa: ANN001
    data = json.loads(json.dumps(path_data))
    edit(data)
    return data


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: d["scenes"][0]["vehicles"][1]["autopilot"].update(target_speed="fast"),
     r"vehicles\[1\]\.autopilot\.target_speed' is str 'fast', expected a number"),
    (lambda d: d["scenes"][0]["vehicles"][1]["autopilot"].update(warp=9.0),
     r"unknown field\(s\) 'warp' in 'scenes\[0\]\.vehicles\[1\]\.autopilot'; allowed: target_speed"),
    (lambda d: d["scenes"][0]["vehicles"][1]["autopilot"].pop("min_gap"),
     r"missing field 'scenes\[0\]\.vehicles\[1\]\.autopilot\.min_gap'"),
    (lambda d: d["scenes"][0]["vehicles"][1]["autopilot"].update(max_accel=-5.0), r"max_accel' = -5\.0; expected >="),
    (lambda d: d["scenes"][0]["vehicles"][2].update(autopilot=None), r"vehicles\[2\]\.autopilot' must be an object"),
    (lambda d: d["scenes"][0]["vehicles"][0].update(x=9999.0), r"vehicles\[0\]\.x'/'y'.*m from lane"),
    (lambda d: d["scenes"][0]["vehicles"][0].update(s=1e6), r"vehicles\[0\]\.s' = 1000000\.0; lane \d+ is"),
    (lambda d: d["scenes"][0]["vehicles"][0].update(x=float("nan")), r"vehicles\[0\]\.x' = nan; expected a finite"),
    (lambda d: d["scenes"][0].update(signal_offset=float("inf")), r"signal_offset' = inf; expected a finite"),
    (lambda d: d["scenes"][0].update(map="highway"), r"scenes\[0\]\.map' = 'highway'; allowed: 'urban'"),
    (lambda d: d["scenes"][0].update(seed=-1), r"scenes\[0\]\.seed' = -1; expected an integer >= 0"),
    (lambda d: d.update(backend="unreal"), r"'backend' = 'unreal'; allowed: lite, carla"),
    (lambda d: d.update(scenes=[]), r"the catalog has no scenes"),
    (lambda d: d["scenes"].__setitem__(0, 5), r"'scenes\[0\]' must be an object, got int"),
])
def test_bad_catalog_fields_are_named(edit, message):
    good = generate_catalog("urban", 1, 0).to_json()
    with pytest.raises(UserInputError, match=message):
        catalog_from_json(_tampered(good, edit))


def test_next_lane_must_follow_the_lane():
    good = generate_catalog("urban", 1, 0).to_json()
    ego = good["scenes"][0]["vehicles"][0]
    successors = load_map("urban").lanes[ego["lane"]].successors
    wrong = next(k for k in range(len(load_map("urban").lanes)) if k not in successors)
    data = _tampered(good, lambda d: d["scenes"][0]["vehicles"][0].update(next_lane=wrong))
    with pytest.raises(UserInputError, match=rf"next_lane' = {wrong} does not follow lane {ego['lane']}; allowed: "):
        catalog_from_json(data)


def test_a_generated_catalog_passes_its_own_validation():
    for map_name in ("urban", "highway"):
        cat = generate_catalog(map_name, 40, 3)
        assert catalog_from_json(json.loads(json.dumps(cat.to_json()))) == cat


def test_vehicles_that_start_inside_each_other_are_refused():
    good = generate_catalog("urban", 1, 0).to_json()

    def stack(d: dict) -> None:
        ego, other = d["scenes"][0]["vehicles"][0], d["scenes"][0]["vehicles"][5]
        other.update({k: ego[k] for k in ("lane", "s", "x", "y", "yaw", "next_lane")})

    with pytest.raises(UserInputError, match=r"'scenes\[0\]\.vehicles\[0\]' and 'scenes\[0\]\.vehicles\[5\]' overlap"):
        catalog_from_json(_tampered(good, stack))


def test_free_flow_traffic_cruises_at_speed_and_only_the_knobs_stop_the_lead(tmp_path):
    """free_flow (the timing members' scenes, docs/scenes.md): the ego on a 25 m/s main line at 90-100 % of
    it with room for a whole episode, its lead 1.5-2.0 s ahead cruising a little slower (so a faster ego
    catches up), no one with spontaneous stops; seeded, valid, and the mixed catalogs are untouched."""
    from genesis_rl.sim.backends import catalog_or_generate
    from genesis_rl.sim.lite.scenes import FREE_FLOW_RUN_M

    road = load_map("highway")
    cat = generate_catalog("highway", 40, 0, traffic="free_flow")
    for sc in cat.scenes:
        ego, lead = sc.vehicles[0], sc.vehicles[1]
        limit = road.speed_limit(ego.lane)
        assert limit == 25.0 and road.length[ego.lane] - ego.s >= FREE_FLOW_RUN_M
        assert 0.9 * limit <= ego.speed <= limit and lead.lane == ego.lane and lead.speed == ego.speed
        headway = (lead.s - ego.s) / ego.speed
        assert 1.5 <= headway <= 2.0
        assert 0.85 * limit <= lead.autopilot["target_speed"] <= 0.95 * limit
        assert all(v.autopilot["stop_rate"] == 0.0 for v in sc.vehicles[1:])
        assert min(v.speed for v in sc.vehicles[1:]) > 0.0  # nobody parked in a free-flowing scene
    assert generate_catalog("highway", 40, 0, traffic="free_flow").to_json() == cat.to_json()
    mixed = generate_catalog("highway", 40, 0)
    assert all(sc.vehicles[1].autopilot["stop_rate"] >= 1.5 for sc in mixed.scenes)  # the paper's leads stop
    assert catalog_or_generate(None, "highway", 40, 0, traffic="free_flow").to_json() == cat.to_json()
    with pytest.raises(UserInputError, match="no lane for free-flowing traffic"):
        generate_catalog("urban", 2, 0, traffic="free_flow")  # urban's roads are short and slow
    with pytest.raises(UserInputError, match="traffic = 'jam'.*allowed: mixed, free_flow"):
        generate_catalog("highway", 2, 0, traffic="jam")
    out = tmp_path / "ff.json"
    done = subprocess.run([sys.executable, "-m", "genesis_rl", "scenes", "--map", "highway", "--count", "3",
                           "--traffic", "free_flow", "--out", str(out), "--quiet"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert load_catalog(out).to_json() == generate_catalog("highway", 3, 0, traffic="free_flow").to_json()


def test_in_free_flow_nobody_starts_between_the_ego_and_its_lead_or_tailgating():
    """Others keep at least free flow's time gap to whoever is ahead in their lane, so the ego's nearest car
    ahead is the placed lead (a car slipped in 8 m ahead of the ego made a lead braking at 6 m/s^2
    unavoidable for any driver in an early try)."""
    from genesis_rl.sim.lite.scenes import FREE_FLOW_TIME_GAP

    for sc in generate_catalog("highway", 40, 0, traffic="free_flow").scenes:
        ego, lead = sc.vehicles[0], sc.vehicles[1]
        between = [v for v in sc.vehicles[3:] if v.lane == ego.lane and ego.s < v.s < lead.s]
        assert between == []
        by_lane: dict[int, list] = {}
        for v in sc.vehicles:
            by_lane.setdefault(v.lane, []).append(v)
        for vs in by_lane.values():
            vs.sort(key=lambda v: v.s)
            for behind, ahead in zip(vs, vs[1:], strict=False):
                if behind.role == "other" or ahead.role == "other":
                    gap = ahead.s - behind.s - (MAKES[ahead.make].length + MAKES[behind.make].length) / 2
                    assert gap >= 2.0 + FREE_FLOW_TIME_GAP * behind.speed - 1e-9


def test_a_catalog_saves_what_asdict_gave_and_bench_catalog_times_it(tmp_path, capsys):
    """The field-by-field serialiser writes exactly what ``dataclasses.asdict`` did (the same keys, order and
    values, the autopilot a copy), and ``genesis-rl bench catalog`` reports every stage."""
    from dataclasses import asdict

    from genesis_rl.commands.cli import main
    from genesis_rl.world.scenes.catalog import _vehicle_json

    catalog = generate_catalog("urban", 3, seed=4)
    for scene in catalog.scenes:
        for v in scene.vehicles:
            got = _vehicle_json(v)
            assert json.dumps(got) == json.dumps(asdict(v)) and list(got) == list(asdict(v))
            if v.autopilot is not None:
                assert got["autopilot"] is not v.autopilot  # a copy: editing the JSON leaves the scene as it was
    assert main(["bench", "catalog", "--scenes", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    for name in ("highway_free_flow", "urban"):
        assert out[name]["vehicles"] == 60 and out[name]["bytes"] > 10_000
        assert all(out[name][k] >= 0 for k in ("save_s", "read_json_s", "parse_s", "load_s"))
    assert main(["bench", "catalog", "--scenes", "0"]) == 2
