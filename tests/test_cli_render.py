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
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.world.knobs import Weather

    scene = generate_catalog("urban", 1, 0).scenes[0]
    backend = LiteBackend()
    try:
        day = backend.create_simulation(scene, seed=0)
        night = backend.create_simulation(scene, seed=0, weather=Weather.preset("clear_night"))
        assert day.observe().rgb.mean() > 4 * night.observe().rgb.mean()  # night straight after day is dark
        assert day.observe().rgb.mean() > 4 * night.observe().rgb.mean()
    finally:
        backend.close()


def _main_err(capsys, *args) -> tuple[int, str]:
    """Run the CLI in-process (bad input fails before any rendering); returns (exit status, stderr)."""
    from genesis_rl.commands.cli import main

    try:
        rc = main(list(args))
    except SystemExit as exc:  # argparse's own errors
        rc = int(exc.code)
    return rc, capsys.readouterr().err


def test_bad_command_lines_exit_2_with_a_message_and_touch_nothing(tmp_path, capsys):
    a_file = tmp_path / "a.json"
    a_file.write_text("{}")
    own = tmp_path / "own"
    own.mkdir()
    (own / "rgb.png").write_bytes(b"mine")  # a folder with one of render's outputs, but not boxes.json
    a_dir = tmp_path / "adir"
    a_dir.mkdir()
    cases = [
        (("scenes", "--map", "urban", "--count", "3", "--seed", "-5", "--out", str(tmp_path / "s.json")),
         "--seed = -5; allowed: an integer >= 0"),
        (("drive", "--episode-seed", "-1", "--out", str(tmp_path / "d")),
         "--episode-seed = -1; allowed: an integer >= 0"),
        (("render", "--out", str(a_file)), f"--out '{a_file}': '{a_file}' is a file; expected a folder"),
        (("scenes", "--map", "urban", "--count", "2", "--out", str(a_dir), "--force"),
         f"output '{a_dir}' is a directory; expected a file path"),
        (("render", "--weather", "fog_density=10,fog_density=90", "--out", str(tmp_path / "r")),
         "--weather: knob 'fog_density' is given twice"),
        (("render", "--weather", "=3", "--out", str(tmp_path / "r")), "--weather: missing knob name in '=3'"),
        (("render", "--weather", "fog=3", "--out", str(tmp_path / "r")), "--weather: unknown knob 'fog'; allowed:"),
        (("render", "--sweep", "--weather", "fog_density=150", "--out", str(tmp_path / "r")),
         "--weather does not apply with --sweep"),
        (("render", "--warmup", "-5", "--out", str(tmp_path / "r")), "--warmup = -5; allowed: an integer >= 0"),
        (("render", "--map", "urban", "--scene", "5000000", "--out", str(tmp_path / "r")),
         "without a catalog at most 5000 are"),
        (("render", "--out", str(own)), f"'{own / 'rgb.png'}' already exists; pass --force"),
        (("drive", "--steps", "5", "--gif-from", "100", "--out", str(tmp_path / "d")),
         "--gif-from must be a step in 0..4 (--steps 5), got 100"),
        (("drive", "--gif", "--no-gif", "--out", str(tmp_path / "d")), "--gif and --no-gif contradict"),
        (("render", "--catalog", str(a_dir), "--out", str(tmp_path / "r")), f"catalog '{a_dir}' is a folder"),
        (("drive", "--weights", str(a_dir), "--steps", "2", "--out", str(tmp_path / "d")),
         f"weights '{a_dir}' is a folder"),
    ]
    for args, message in cases:
        rc, err = _main_err(capsys, *args)
        assert rc == 2 and message in err, (args, rc, err)
        assert "Traceback" not in err
    assert (own / "rgb.png").read_bytes() == b"mine"
    assert not (tmp_path / "r").exists() and not (tmp_path / "d").exists()


def test_render_refuses_a_catalog_of_another_backend(tmp_path, capsys):
    from genesis_rl.sim.lite.scenes import generate_catalog

    data = generate_catalog("urban", 1, 0).to_json()
    data["backend"] = "carla"
    path = tmp_path / "carla.json"
    path.write_text(json.dumps(data))
    rc, err = _main_err(capsys, "render", "--catalog", str(path), "--out", str(tmp_path / "r"))
    assert rc == 2 and "holds carla scenes; render draws lite scenes" in err
    rc, err = _main_err(capsys, "drive", "--catalog", str(path), "--out", str(tmp_path / "d"))
    assert rc == 2 and "holds carla scenes; pass --backend carla" in err
