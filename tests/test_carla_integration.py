"""On a real CARLA 0.9.16 server: one short episode, then drive, a 2-episode evaluate and a 512-step train
with the built-in systems; runs only when CARLA_HOST is set.

    CARLA_HOST=localhost [CARLA_PORT=2000] [CARLA_TM_PORT=8000] [CARLA_MAP=Town10HD_Opt] \
        python -m pytest -q tests/test_carla_integration.py
"""

from __future__ import annotations

import os

import numpy as np
import pytest

HOST = os.environ.get("CARLA_HOST")
if not HOST:
    pytest.skip("set CARLA_HOST (and CARLA_PORT, default 2000) to the address of a running CARLA 0.9.16 server "
                "to run the CARLA integration tests", allow_module_level=True)
carla = pytest.importorskip("carla")

from genesis_rl.carla_backend.backend import CarlaBackend  # noqa: E402
from genesis_rl.carla_backend.scenes import generate_catalog  # noqa: E402
from genesis_rl.carla_backend.weather import same_weather, to_carla  # noqa: E402
from genesis_rl.knobs import Weather  # noqa: E402
from genesis_rl.sim.interface import CameraConfig, VehicleControl  # noqa: E402

PORT = int(os.environ.get("CARLA_PORT", "2000"))
TM_PORT = int(os.environ.get("CARLA_TM_PORT", "8000"))
MAP = os.environ.get("CARLA_MAP", "Town10HD_Opt")
STEPS = 40


@pytest.fixture(scope="module")
def backend():
    with CarlaBackend(HOST, PORT, timeout=20.0, tm_port=TM_PORT) as b:
        yield b


def test_one_short_episode(backend):
    assert MAP in backend.map_names()
    world = backend.load_map(MAP)
    carla_map = backend.map_of(world)
    catalog = generate_catalog(carla_map, MAP, 1, seed=0, spawn_points=carla_map.get_spawn_points())
    scene = catalog.scenes[0]
    before = world.get_settings()
    camera = CameraConfig(width=320, height=240)
    weather = Weather.preset("heavy_rain_night").replace(fog_density=40.0)
    with backend.create_simulation(scene, seed=0, weather=weather, camera=camera) as sim:
        settings = sim.world.get_settings()
        assert settings.synchronous_mode and settings.fixed_delta_seconds == pytest.approx(0.05)
        assert same_weather(sim.world.get_weather(), to_carla(weather))
        actors = sim.actors()
        assert actors[0].role == "ego" and len(actors) >= len(scene.vehicles) - len(sim.skipped)
        first = sim.observe()
        assert first.step == 0 and first.rgb.shape == (240, 320, 3) and first.depth.shape == (240, 320)
        sim.apply_ego_control(VehicleControl(throttle=0.5))
        for i in range(STEPS):
            sim.set_weather(weather.replace(fog_density=float(40 + i)))
            result = sim.tick()
            assert result.step == i + 1 and result.time == pytest.approx((i + 1) * 0.05)
        frame = sim.observe()
        assert sim.step_count == STEPS and frame.step == STEPS
        assert frame.rgb.dtype == np.uint8 and frame.depth.dtype == np.float32
        assert 0.0 < float(frame.depth.min()) and float(frame.depth.max()) <= 1000.0
        assert sim.world.get_weather().fog_density == pytest.approx(40 + STEPS - 1, abs=1e-3)
        for box in frame.boxes:
            assert 0 <= box.x0 < box.x1 <= 320 and 0 <= box.y0 < box.y1 <= 240 and box.vehicle_id > 0
        assert sim.ego().speed > 0.5  # half throttle for 2 s moves the ego
        lead = sim.lead()
        assert lead is None or lead.gap >= 0.0
        ids = sim.carla_actor_ids()
    after = world.get_settings()
    assert after.synchronous_mode == before.synchronous_mode
    assert after.fixed_delta_seconds == before.fixed_delta_seconds
    if after.synchronous_mode:
        world.tick()
    else:
        world.wait_for_tick()
    assert len(world.get_actors(ids)) == 0  # everything we spawned is gone


# -- the commands a user runs, end to end on the server (the paper's system: the built-in one) ------------------
def _cli(*args: str, timeout: float = 1800.0):
    import subprocess
    import sys

    server = ["--backend", "carla", "--carla-host", HOST, "--carla-port", str(PORT), "--carla-tm-port", str(TM_PORT)]
    r = subprocess.run([sys.executable, "-m", "genesis_rl", *args, *server], capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.fixture(scope="module")
def server_catalog(tmp_path_factory, backend):
    path = tmp_path_factory.mktemp("carla") / "catalog.json"
    world = backend.load_map(MAP)
    carla_map = backend.map_of(world)
    generate_catalog(carla_map, MAP, 4, seed=0, spawn_points=carla_map.get_spawn_points()).save(path)
    backend.close()  # the commands below connect on their own; this connection's traffic manager is shut down
    return path


@pytest.mark.parametrize("system", ["builtin", "oracle"])
def test_drive_with_a_builtin_system(tmp_path, server_catalog, system):
    out = tmp_path / "drive"
    _cli("drive", "--catalog", str(server_catalog), "--scene", "0", "--system", system, "--steps", "100",
         "--out", str(out))
    import pyarrow.parquet as pq

    telemetry = pq.read_table(next(out.rglob("*.parquet"))).to_pydict()
    assert len(telemetry["ego_speed"]) == 100 and max(telemetry["ego_speed"]) > 1.0  # it drove on its route


def test_evaluate_two_episodes(tmp_path, server_catalog):
    out = tmp_path / "eval"
    _cli("evaluate", "--policies", "sunny", "--catalog", str(server_catalog), "--scenes", "2", "--seed", "0",
         "--steps", "100", "--out", str(out))
    assert (out / "summary.json").exists() and len(list((out / "episodes" / "sunny").glob("*.json"))) == 2


def test_train_512_steps(tmp_path, server_catalog):
    out = tmp_path / "run"
    _cli("train", "--config", "configs/quickstart.toml", "--catalog", str(server_catalog), "--steps", "512",
         "--n-steps", "512", "--out", str(out))
    assert (out / "agent.zip").exists()
