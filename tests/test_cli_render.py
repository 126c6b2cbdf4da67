import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.render


def _run(*args):
    return subprocess.run([sys.executable, "-m", "genesis_rl", *args], capture_output=True, text=True)


def test_render_writes_rgb_depth_boxes_and_refuses_overwrite(tmp_path):
    out = tmp_path / "r"
    r = _run("render", "--map", "urban", "--scene", "0", "--weather", "fog_density=60,sun_altitude_angle=10",
             "--out", str(out))
    assert r.returncode == 0, r.stderr
    for name in ("rgb.png", "depth.png", "boxes.png", "boxes.json"):
        assert (out / name).is_file()
    info = json.loads((out / "boxes.json").read_text())
    assert info["weather"]["fog_density"] == 60 and info["width"] == 320
    r = _run("render", "--map", "urban", "--out", str(out))
    assert r.returncode == 2 and "--force" in r.stderr


@pytest.mark.parametrize("weather, field", [("fog_density=abc", "fog_density"), ("rain=5", "unknown knob 'rain'"),
                                            ("fog_density=101", "allowed 0..100")])
def test_render_bad_weather_exits_2_naming_the_field(tmp_path, weather, field):
    r = _run("render", "--map", "urban", "--weather", weather, "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and field in r.stderr and "Traceback" not in r.stderr


def test_each_observe_returns_the_current_frame_not_the_previous_one():
    from genesis_rl.knobs import Weather
    from genesis_rl.lite.backend import LiteBackend
    from genesis_rl.scenes.lite_generator import generate_catalog

    scene = generate_catalog("urban", 1, 0).scenes[0]
    backend = LiteBackend()
    try:
        day = backend.create_simulation(scene, seed=0)
        night = backend.create_simulation(scene, seed=0, weather=Weather.preset("clear_night"))
        assert day.observe().rgb.mean() > 4 * night.observe().rgb.mean()  # night straight after day is dark
        assert day.observe().rgb.mean() > 4 * night.observe().rgb.mean()
    finally:
        backend.close()
