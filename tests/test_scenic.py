"""Scenic 3 as the scene generator (the paper's): the shipped program on the lite maps' OpenDRIVE export
and on a carla.Map, into the catalog schema. Skipped without the ``scenic`` extra."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

pytest.importorskip("scenic")

from genesis_rl.sim.backends import catalog_from_json  # noqa: E402
from genesis_rl.sim.lite.maps import load_map  # noqa: E402
from genesis_rl.sim.lite.scenes import check_catalog  # noqa: E402
from genesis_rl.sim.scenic.generator import N_VEHICLES, carla_catalog, lite_catalog  # noqa: E402


def _layout_ok(scene, road_map) -> None:
    ego, lead, neighbour, *others = scene.vehicles
    assert [ego.role, lead.role, neighbour.role] == ["ego", "lead", "neighbour"] and len(others) == N_VEHICLES - 3
    assert {o.role for o in others} == {"other"}
    for v in (lead, neighbour):  # ahead of the ego, going its way
        dx, dy = v.x - ego.x, v.y - ego.y
        assert dx * math.cos(ego.yaw) + dy * math.sin(ego.yaw) > 0 and math.cos(v.yaw - ego.yaw) > 0.5
    assert 5.0 <= math.hypot(lead.x - ego.x, lead.y - ego.y) <= 45.0
    if road_map is not None:
        assert lead.lane in (ego.lane, *road_map.lanes[ego.lane].successors) or road_map.lanes[lead.lane].junction >= 0
        assert neighbour.lane != ego.lane
    for o in others:
        assert math.hypot(o.x - ego.x, o.y - ego.y) < 90.0 + 5.0


def test_scenic_lite_catalog_validates_and_is_deterministic() -> None:
    road_map = load_map("urban")
    cat = lite_catalog("urban", 2, seed=5)
    check_catalog(cat)  # lanes, poses and overlaps, as the lite generator's catalogs
    assert catalog_from_json(json.loads(json.dumps(cat.to_json()))) == cat
    for scene in cat.scenes:
        _layout_ok(scene, road_map)
    assert lite_catalog("urban", 2, seed=5) == cat
    assert lite_catalog("urban", 1, seed=6).scenes[0] != cat.scenes[0]


def test_scenic_on_a_carla_map_writes_the_carla_schema() -> None:
    carla = pytest.importorskip("carla")
    from genesis_rl.sim.carla.spawn import plan_scene
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive

    cmap = carla.Map("highway", to_opendrive(load_map("highway")))
    cat = carla_catalog(cmap, "highway", 1, seed=0)
    assert cat.backend == "carla" and catalog_from_json(json.loads(json.dumps(cat.to_json()))) == cat
    _layout_ok(cat.scenes[0], None)
    specs = plan_scene(cat.scenes[0], cmap)  # the CARLA backend spawns it where it says
    assert len(specs) == N_VEHICLES


def test_scenes_command_with_the_scenic_generator(tmp_path) -> None:
    out = tmp_path / "cat.json"
    r = subprocess.run([sys.executable, "-m", "genesis_rl", "scenes", "--generator", "scenic", "--map", "highway",
                        "--count", "1", "--seed", "3", "--out", str(out), "--quiet"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["scenes"] == 1 and catalog_from_json(json.loads(out.read_text())).map == "highway"


def test_the_export_loads_as_a_scenic_road_network(tmp_path) -> None:
    from scenic.domains.driving.roads import Network

    from genesis_rl.sim.lite.maps.opendrive import to_opendrive

    lite = load_map("urban")
    path = tmp_path / "urban.xodr"
    path.write_text(to_opendrive(lite))
    net = Network.fromFile(str(path), useCache=False)
    assert len(net.roads) == len(lite.roads) and len(net.intersections) == len(lite.junctions)
    assert len(net.lanes) == len(lite.lanes)  # road lanes and junction connectors, one to one
    with_right = [s for s in net.laneSections if s._laneToRight is not None]
    assert len(with_right) == sum(1 for ln in lite.lanes if ln.road >= 0 and ln.right >= 0)
