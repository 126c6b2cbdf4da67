"""The CARLA backend without a server: the real ``carla`` client package (0.9.16) and an offline ``carla.Map``.

Skipped as a module when the optional extra is not installed (pip install -e .[carla]).
"""

from __future__ import annotations

import json
import math
import socket
import sys
import time

import numpy as np
import pytest

carla = pytest.importorskip("carla")

from genesis_rl.core.errors import UserInputError  # noqa: E402
from genesis_rl.sim.backends import catalog_from_json  # noqa: E402
from genesis_rl.sim.carla.connection import (  # noqa: E402
    CarlaConnectionError,
    CarlaServerLost,
    guarded,
)
from genesis_rl.sim.carla.lanes import lane_from_key, lane_key  # noqa: E402
from genesis_rl.sim.carla.lead import lane_path, lead_on_path  # noqa: E402
from genesis_rl.sim.carla.projection import (  # noqa: E402
    box_in_camera,
    ground_truth_box,
    project_box,
    world_to_optical,
)
from genesis_rl.sim.carla.scenes import generate_catalog  # noqa: E402
from genesis_rl.sim.carla.sensors import bgra_to_rgb, decode_depth, encode_depth  # noqa: E402
from genesis_rl.sim.carla.spawn import BLUEPRINTS, SPAWN_LIFT, plan_scene  # noqa: E402
from genesis_rl.sim.carla.weather import (  # noqa: E402
    carla_preset,
    carla_preset_names,
    carla_weather_fields,
    from_carla,
    to_carla,
)
from genesis_rl.sim.interface import CameraConfig  # noqa: E402
from genesis_rl.world.knobs import KNOBS, PRESETS, Weather, weather_knob_names  # noqa: E402
from genesis_rl.world.scenes.catalog import Scene, VehicleSpec  # noqa: E402

# A straight road along +x, 200 m: lanes -1 and -2 drive towards +x (right of the reference line, which is
# +y in CARLA's left-handed frame: y = 1.75 and 5.25), lane 1 drives towards -x (y = -1.75).
STRAIGHT_XODR = """<?xml version="1.0" standalone="yes"?>
<OpenDRIVE>
  <header revMajor="1" revMinor="4" name="straight" version="1.00" north="0" south="0" east="0" west="0"/>
  <road name="main" length="200.0" id="0" junction="-1">
    <link/>
    <type s="0.0" type="town"><speed max="50" unit="km/h"/></type>
    <planView>
      <geometry s="0.0" x="0.0" y="0.0" hdg="0.0" length="200.0"><line/></geometry>
    </planView>
    <elevationProfile><elevation s="0" a="0" b="0" c="0" d="0"/></elevationProfile>
    <lateralProfile/>
    <lanes>
      <laneSection s="0.0">
        <left>
          <lane id="1" type="driving" level="false"><link/><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane>
        </left>
        <center><lane id="0" type="none" level="false"><link/></lane></center>
        <right>
          <lane id="-1" type="driving" level="false"><link/><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane>
          <lane id="-2" type="driving" level="false"><link/><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane>
        </right>
      </laneSection>
    </lanes>
  </road>
</OpenDRIVE>
"""


@pytest.fixture(scope="module")
def straight_map():
    return carla.Map("Straight", STRAIGHT_XODR)


# -- weather -------------------------------------------------------------------------------------------------
WEATHER_KNOBS = weather_knob_names()  # the actor knobs (lead_decel, cut_in_ttc) have no WeatherParameters field


def test_knobs_are_exactly_the_weather_parameters_fields():
    assert set(carla_weather_fields()) == set(WEATHER_KNOBS)
    assert len(WEATHER_KNOBS) == 14 and set(KNOBS) - set(WEATHER_KNOBS) == {
        "lead_decel", "cut_in_ttc", "vehicle_percentage_speed_difference", "ignore_lights_percentage",
        "cut_in_relative_speed"}


@pytest.mark.parametrize("name", sorted(WEATHER_KNOBS))
def test_each_knob_sets_its_field_and_reads_back(name):
    spec = KNOBS[name]
    value = round(spec.low + 0.37 * spec.span, 2)
    weather = Weather.default().replace(**{name: value})
    params = to_carla(weather)
    assert getattr(params, name) == pytest.approx(value, abs=1e-4)
    for other in WEATHER_KNOBS:  # every other field carries its own knob, not CARLA's constructor default
        assert getattr(params, other) == pytest.approx(weather[other], abs=1e-4)
    assert from_carla(params) == weather


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_our_presets_round_trip(name):
    weather = Weather.preset(name)
    assert from_carla(to_carla(weather)) == weather


def test_carla_presets_read_as_knobs():
    names = carla_preset_names()
    assert len(names) == 22 and "Default" not in names  # 23 presets, Default (-1 = keep the map's) left out
    for name in names:
        params = getattr(carla.WeatherParameters, name)
        weather = carla_preset(name)
        for field in WEATHER_KNOBS:
            spec = KNOBS[field]
            raw = float(getattr(params, field))
            expected = raw % 360.0 if spec.wraps else min(max(raw, spec.low), spec.high)
            assert weather[field] == pytest.approx(expected, abs=1e-4), (name, field)
    hard = carla_preset("HardRainNight")
    assert (hard["precipitation"], hard["precipitation_deposits"], hard["cloudiness"]) == (100.0, 90.0, 100.0)
    assert (hard["sun_altitude_angle"], hard["sun_azimuth_angle"], hard["wetness"]) == (-90.0, 359.0, 100.0)
    with pytest.raises(UserInputError, match="HardRainNight"):
        carla_preset("HardRain")


# -- projection --------------------------------------------------------------------------------------------
CAM = CameraConfig(width=200, height=100, fov_deg=90.0)  # focal length 200 / (2 tan 45 deg) = 100 px


def test_projection_by_hand():
    """Camera at (0, 0, 2) looking along CARLA +y (yaw 90; its right is -x). A 4 x 2 x 1 m box turned the
    same way, 20 m ahead, 3 m to the right, 1 m below: its faces are at depth 18 and 22, lateral 2..4 m,
    vertical -1.5..-0.5 m. u = 100 + 100 * lateral / depth, v = 50 - 100 * up / depth."""
    camera_tf = carla.Transform(carla.Location(0.0, 0.0, 2.0), carla.Rotation(yaw=90.0))
    bbox = carla.BoundingBox(carla.Location(0.0, 0.0, 0.0), carla.Vector3D(2.0, 1.0, 0.5))
    actor_tf = carla.Transform(carla.Location(-3.0, 20.0, 1.0), carla.Rotation(yaw=90.0))
    box = box_in_camera(bbox, actor_tf, camera_tf)
    u0, v0, u1, v1, truncated = project_box(box, CAM.intrinsics(), CAM.width, CAM.height)
    assert u0 == pytest.approx(100 + 100 * 2 / 22, abs=1e-4)  # near edge of the far face
    assert u1 == pytest.approx(100 + 100 * 4 / 18, abs=1e-4)  # far edge of the near face
    assert v0 == pytest.approx(50 + 100 * 0.5 / 22, abs=1e-4)
    assert v1 == pytest.approx(50 + 100 * 1.5 / 18, abs=1e-4)
    assert not truncated
    # the same corners through BoundingBox.get_world_vertices and the camera's inverse matrix
    world = np.array([[p.x, p.y, p.z] for p in bbox.get_world_vertices(actor_tf)])
    np.testing.assert_allclose(np.sort(world_to_optical(world, camera_tf), axis=0), np.sort(box.vertices(), axis=0),
                               atol=1e-4)


def test_projection_clips_at_near_plane_and_border():
    """A box from 2 m behind to 4 m ahead, 2..4 m to the right: the near-plane cut reaches the right border."""
    box = box_in_camera(carla.BoundingBox(carla.Location(), carla.Vector3D(3.0, 1.0, 1.0)),
                        carla.Transform(carla.Location(1.0, 3.0, 0.0)), carla.Transform())
    u0, v0, u1, v1, truncated = project_box(box, CAM.intrinsics(), CAM.width, CAM.height)
    assert (u0, v0, u1, v1, truncated) == (pytest.approx(150.0, abs=1e-4), 0.0, 200.0, 100.0, True)
    behind = box_in_camera(carla.BoundingBox(carla.Location(), carla.Vector3D(1.0, 1.0, 1.0)),
                           carla.Transform(carla.Location(-10.0, 0.0, 0.0)), carla.Transform())
    assert project_box(behind, CAM.intrinsics(), CAM.width, CAM.height) is None


def test_occlusion_against_depth_image():
    """A 4 x 2 x 2 m box 20 m straight ahead shows only its near face: pixels whose centres fall within
    100 +- 100/18 (columns 94..105, rows 44..55) at depth 18 m. Hiding columns 94..98 behind a 5 m object
    leaves columns 99..105: 7 of 12 visible."""
    box = box_in_camera(carla.BoundingBox(carla.Location(), carla.Vector3D(2.0, 1.0, 1.0)),
                        carla.Transform(carla.Location(20.0, 0.0, 0.0)), carla.Transform())
    depth = np.full((CAM.height, CAM.width), 1000.0, dtype=np.float32)
    depth[44:56, 94:106] = 18.0
    gt = ground_truth_box(7, box, CAM.intrinsics(), depth)
    assert (gt.vehicle_id, gt.xyxy, gt.distance, gt.visible_fraction, gt.truncated) == (7, (94, 44, 106, 56), 18.0,
                                                                                        1.0, False)
    depth[:, 94:99] = 5.0
    gt = ground_truth_box(7, box, CAM.intrinsics(), depth)
    assert gt.xyxy == (99, 44, 106, 56)
    assert gt.visible_fraction == pytest.approx(7 / 12)
    depth[:, 94:106] = 5.0
    assert ground_truth_box(7, box, CAM.intrinsics(), depth) is None


def test_depth_and_rgb_decoding():
    # one pixel per channel: R weighs 1, G 256, B 65536 units of 1000 m / (256^3 - 1)
    raw = bytes([0, 0, 255, 255, 0, 1, 0, 255, 1, 0, 0, 255])  # BGRA: R=255 | G=1 | B=1
    unit = 1000.0 / (256**3 - 1)
    np.testing.assert_allclose(decode_depth(raw, 3, 1)[0], [255 * unit, 256 * unit, 65536 * unit], rtol=1e-6)
    depth = np.array([[0.5, 18.0], [123.456, 999.0]])
    np.testing.assert_allclose(decode_depth(encode_depth(depth), 2, 2), depth, atol=1e-4)
    rgb = bgra_to_rgb(bytes([10, 20, 30, 255]), 1, 1)
    assert rgb.tolist() == [[[30, 20, 10]]]


# -- spawning a catalog scene ----------------------------------------------------------------------------------
def _spec(role, make, x, y, yaw, color=(1.0, 0.0, 0.5)):
    return VehicleSpec(role, make, "x", color, 0, 0.0, x, y, yaw, 5.0, 0,
                       None if role == "ego" else {"target_speed": 8.0, "min_gap": 2.0})


def test_scene_to_spawn_transforms(straight_map):
    """Catalog poses are in our right-handed frame (y = -CARLA y, yaw CCW); each snaps to its lane centre."""
    scene = Scene(0, "Straight", 1, 0.0, (
        _spec("ego", "sedan", 50.0, -1.75, 0.0),
        _spec("lead", "truck", 70.0, -1.6, 0.05),  # off-centre: snapped to lane -1
        _spec("neighbour", "van", 60.0, -5.25, 0.0),
        _spec("other", "bus", 80.0, 1.75, math.pi),  # oncoming lane
    ))
    specs = plan_scene(scene, straight_map)
    expected = [(50.0, 1.75, 0.0), (70.0, 1.75, 0.0), (60.0, 5.25, 0.0), (80.0, -1.75, 180.0)]
    for spec, (x, y, yaw) in zip(specs, expected, strict=True):
        loc, rot = spec.transform.location, spec.transform.rotation
        assert (loc.x, loc.y, loc.z) == (pytest.approx(x, abs=0.05), pytest.approx(y, abs=1e-3),
                                         pytest.approx(SPAWN_LIFT, abs=1e-3))
        assert rot.yaw % 360.0 == pytest.approx(yaw, abs=1e-3)
    assert [s.role_name for s in specs] == ["hero", "genesis_lead_1", "genesis_neighbour_2", "genesis_other_3"]
    assert specs[0].color == "255,0,128" and specs[0].autopilot is None
    assert specs[1].blueprint_ids == BLUEPRINTS["truck"] and specs[3].blueprint_ids == ("vehicle.mitsubishi.fusorosa",)
    lost = Scene(1, "Straight", 1, 0.0, (_spec("ego", "sedan", 50.0, 40.0, 0.0),))
    with pytest.raises(UserInputError, match="scenes --backend carla --map Straight"):
        plan_scene(lost, straight_map)


def test_scene_generation_on_offline_map(straight_map):
    cat = generate_catalog(straight_map, "Straight", 3, seed=11, n_vehicles=10)
    assert cat.backend == "carla" and len(cat.scenes) == 3
    for scene in cat.scenes:
        ego, lead, nb, *others = scene.vehicles
        assert [ego.role, lead.role, nb.role] == ["ego", "lead", "neighbour"] and len(others) == 7
        assert lane_from_key(ego.lane) == (0, -1)  # the only lane with a same-direction lane to its right
        assert lead.lane == ego.lane and 15.0 <= lead.x - ego.x <= 40.0 + 0.1
        assert lane_from_key(nb.lane) == (0, -2) and 6.0 <= nb.x - ego.x <= 20.0 + 0.1
        for v in scene.vehicles:
            assert math.hypot(v.x - ego.x, v.y - ego.y) < 90.0 + 20.0
        xy = {(round(v.x, 1), round(v.y, 1)) for v in scene.vehicles}
        assert len(xy) == len(scene.vehicles)
        specs = plan_scene(scene, straight_map)  # the generator's output spawns where it says
        for v, s in zip(scene.vehicles, specs, strict=True):
            assert (s.transform.location.x, -s.transform.location.y) == (pytest.approx(v.x, abs=1e-3),
                                                                         pytest.approx(v.y, abs=1e-3))
    assert catalog_from_json(json.loads(json.dumps(cat.to_json()))) == cat  # the shared schema validates it
    assert generate_catalog(straight_map, "Straight", 3, seed=11, n_vehicles=10) == cat
    assert generate_catalog(straight_map, "Straight", 3, seed=12, n_vehicles=10) != cat
    assert lane_from_key(lane_key(1234, -3)) == (1234, -3)


def test_lead_along_lane(straight_map):
    wp = straight_map.get_waypoint(carla.Location(50.0, 1.75, 0.0))
    path = lane_path(wp)
    assert path[0].tolist() == pytest.approx([50.0, 1.75]) and path[-1][0] == pytest.approx(150.0)
    others = np.array([[90.0, 1.75], [70.0, 5.25], [80.0, 2.5], [30.0, 1.75]])  # ahead, next lane, ahead, behind
    lead = lead_on_path(path, np.array([50.0, 1.75]), 2.3, others, np.full(4, 2.0), np.array([1.0, 2, 3, 4]),
                        np.array([4, 5, 6, 7]))
    assert (lead.vehicle_id, lead.gap, lead.speed) == (6, pytest.approx(80.0 - 50.0 - 2.3 - 2.0), 3.0)


# -- errors a user sees ------------------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_no_server_gives_clear_error_after_the_timeout():
    from genesis_rl.sim.carla.backend import CarlaBackend

    port = _free_port()
    t0 = time.monotonic()
    with pytest.raises(CarlaConnectionError) as info:
        CarlaBackend(host="127.0.0.1", port=port, timeout=1.0)
    elapsed = time.monotonic() - t0
    msg = str(info.value)
    assert isinstance(info.value, UserInputError)  # the CLI prints it and exits with status 2
    assert f"127.0.0.1:{port}" in msg and "CarlaUE4.sh -RenderOffScreen" in msg and "docs/carla.md" in msg
    assert "nothing listens" in msg and "(connection refused)" in msg  # the probe says so without waiting
    assert elapsed < 5.0


def test_server_lost_mid_episode_is_named():
    def tick():
        raise RuntimeError("time-out of 10000ms while waiting for the simulator, make sure ...")

    with pytest.raises(CarlaServerLost, match=r"localhost:2000 stopped answering while ticking"):
        guarded("localhost", 2000, "ticking", tick)

    def bad():
        raise RuntimeError("Spawn failed because of collision at spawn position")

    with pytest.raises(RuntimeError, match="Spawn failed"):
        guarded("localhost", 2000, "spawning", bad)


def test_missing_client_names_the_install_command(monkeypatch):
    from genesis_rl.sim.carla import require_carla

    monkeypatch.setitem(sys.modules, "carla", None)  # makes `import carla` raise ImportError
    with pytest.raises(UserInputError, match=r"pip install -e \.\[carla\]"):
        require_carla()


def test_backend_flags_and_factory():
    import argparse

    from genesis_rl.sim.backends import add_backend_arguments, make_backend

    parser = argparse.ArgumentParser()
    add_backend_arguments(parser)
    args = parser.parse_args(["--backend", "carla", "--carla-host", "sim.local", "--carla-port", "2345"])
    # the traffic manager's port follows the server's unless given (issue 36: 8000 for every run collided)
    assert (args.backend, args.carla_host, args.carla_port, args.carla_tm_port) == ("carla", "sim.local", (2345,), None)
    with pytest.raises(UserInputError, match="allowed: lite, carla"):
        make_backend("unreal")


def test_env_config_switches_backend_by_one_key() -> None:
    from genesis_rl.env.genesis_env import EnvConfig

    assert EnvConfig().backend == "lite"
    with pytest.raises(UserInputError, match="env.backend = 'carla' needs env.catalog"):
        EnvConfig(backend="carla")
    with pytest.raises(UserInputError, match="env.backend = 'unreal' is unknown; allowed: lite, carla"):
        EnvConfig(backend="unreal")
    assert EnvConfig(backend="carla", catalog="town05.json", carla_port=2010).carla_port == 2010
