"""The system under test: plug-in loading, depth localisation, matching, the closed loop and its records."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import textwrap

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.geometry import frame_iou, iou_matrix
from genesis_rl.sim.interface import GroundTruthBox
from genesis_rl.sut.system.protocol import load_system
from genesis_rl.world.knobs import Weather
from genesis_rl.world.weather_schedule import load_schedule, save_schedule


def _box(vid: int, xyxy, distance=20.0, vis=1.0) -> GroundTruthBox:
    return GroundTruthBox(vid, *xyxy, distance=distance, visible_fraction=vis, truncated=False)


# -- matching ------------------------------------------------------------------------------------------
def test_iou_matrix_known_values() -> None:
    m = iou_matrix(np.array([[0, 0, 10, 10]]), np.array([[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30]]))
    np.testing.assert_allclose(m, [[1.0, 50 / 150, 0.0]])


def test_frame_iou_misses_count_zero_and_empty_view_is_one() -> None:
    gt = [_box(1, (0, 0, 20, 20)), _box(2, (40, 0, 60, 20)), _box(3, (80, 0, 90, 20), distance=80.0)]
    iou, per = frame_iou(gt, np.array([[0, 0, 20, 20]]))
    assert per == {1: 1.0, 2: 0.0}  # vehicle 3 is beyond the in-view range and does not count
    assert iou == pytest.approx(0.5)
    assert frame_iou([], np.zeros((0, 4)))[0] == 1.0
    assert frame_iou(gt[:2], np.zeros((0, 4)))[0] == 0.0


# -- plug-in loading -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("no_colon_here", "not an import path"),
        ("genesis_rl.nonexistent_module:X", "cannot import module"),
        ("genesis_rl.sut.system.builtin:NoSuchClass", "has no class"),
        ("genesis_rl.world.knobs:KnobSpec", "lacks the protocol's methods: reset, step, identity"),
    ],
)
def test_load_system_errors_name_the_problem(spec: str, message: str) -> None:
    with pytest.raises(UserInputError, match=message):
        load_system(spec)


def test_yolo_adapter_never_downloads_and_says_what_to_install(tmp_path) -> None:
    with pytest.raises(UserInputError, match="needs --weights PATH"):
        load_system("yolo")
    with pytest.raises(UserInputError, match="'.*missing.pt' does not exist \\(nothing is downloaded"):
        load_system("yolo", weights=str(tmp_path / "missing.pt"))


def test_yolo_adapter_without_ultralytics_names_the_extra(tmp_path, monkeypatch) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "ultralytics", None)  # as if not installed
    weights = tmp_path / "yolov5s.pt"
    weights.write_bytes(b"x")
    with pytest.raises(UserInputError, match="pip install -e '.\\[yolo\\]'"):
        load_system("yolo", weights=str(weights))


def test_yolo_adapter_switches_ultralytics_offline_before_importing_it(tmp_path, monkeypatch) -> None:
    """ultralytics treats YOLO_OFFLINE as offline only when it reads "true" (utils.is_online); "1" made it
    still probe the network before each model load."""
    import sys

    monkeypatch.setenv("YOLO_OFFLINE", "")  # so that monkeypatch restores the caller's value afterwards
    monkeypatch.delenv("YOLO_OFFLINE")
    monkeypatch.setitem(sys.modules, "ultralytics", None)
    weights = tmp_path / "yolov5s.pt"
    weights.write_bytes(b"x")
    with pytest.raises(UserInputError):
        load_system("yolo", weights=str(weights))
    assert os.environ["YOLO_OFFLINE"].lower() == "true"


TINY_SYSTEM = textwrap.dedent(
    '''
    from genesis_rl.sim.interface import VehicleControl
    from genesis_rl.sut.system.protocol import SystemOutput


    class CreepForward:
        """Throttle 0.3, never brakes, sees nothing."""

        def reset(self, context):
            self.steps = 0

        def step(self, frame, ego, time_s):
            self.steps += 1
            return SystemOutput(VehicleControl(throttle=0.3), [], None, "creep")

        def identity(self):
            return {"class": "tiny_user_system:CreepForward"}
    '''
)


@pytest.fixture(scope="module")
def backend():
    from genesis_rl.sim.lite.backend import LiteBackend

    with LiteBackend() as b:
        yield b


@pytest.fixture(scope="module")
def highway_scenes():
    from genesis_rl.sim.lite.scenes import generate_catalog

    return generate_catalog("highway", 6, seed=0)


@pytest.mark.render
def test_user_system_loaded_by_import_path_drives_an_episode(tmp_path, monkeypatch, backend, highway_scenes) -> None:
    from genesis_rl.loop.drive import run_episode

    (tmp_path / "tiny_user_system.py").write_text(TINY_SYSTEM)
    monkeypatch.syspath_prepend(str(tmp_path))
    system = load_system("tiny_user_system:CreepForward")
    result = run_episode(backend, highway_scenes.scene(0), system, lambda _: Weather.default(), 40, seed=0)
    assert system.steps == 41  # the first frame, then one per step
    assert [r.ego.status for r in result.records] == ["creep"] * 40
    assert result.records[-1].ego.throttle == 0.3
    assert result.identity == {"class": "tiny_user_system:CreepForward"}


# -- depth localisation ----------------------------------------------------------------------------------
@pytest.mark.render
def test_depth_localisation_within_10_percent_at_30_m(backend, highway_scenes) -> None:
    """Localise every clearly visible vehicle within 30 m from its true box and the depth image; compare
    with the forward distance to the nearest corner of its true footprint (computed from actor states)."""
    from genesis_rl.sim.lite.collisions import box_corners
    from genesis_rl.sut.system.localisation import box_depth, localise

    errors = []
    for idx in range(4):
        with backend.create_simulation(highway_scenes.scene(idx), seed=1) as sim:
            for _ in range(20):
                sim.tick()
            frame = sim.observe()
            actors = sim.actors()
            ego = actors[0]
            cam = sim.camera
            for b in frame.boxes:
                if b.distance > 30.0 or b.visible_fraction < 0.6 or b.truncated:
                    continue
                est = localise(b.xyxy, box_depth(frame.depth, b.xyxy), cam)
                a = actors[b.vehicle_id]
                corners = box_corners(a.x, a.y, a.yaw, a.length, a.width)
                fwd = (corners[:, 0] - ego.x) * math.cos(ego.yaw) + (corners[:, 1] - ego.y) * math.sin(ego.yaw)
                true_forward = float(fwd.min())
                errors.append(abs(est[0] - true_forward) / true_forward)
    assert len(errors) >= 8
    assert max(errors) < 0.10, errors


# -- weather schedules -----------------------------------------------------------------------------------
def test_schedule_round_trip_and_errors(tmp_path) -> None:
    base = Weather.default()
    weathers = [base.replace(fog_density=float(i)) for i in range(5)]
    p = tmp_path / "s.csv"
    save_schedule(p, weathers, ["fog_density", "precipitation"])
    assert load_schedule(p, base, 5) == weathers
    with pytest.raises(UserInputError, match="has 5 rows; it needs one per step \\(6\\)"):
        load_schedule(p, base, 6)
    bad = tmp_path / "bad.csv"
    bad.write_text("step,fog,precipitation\n0,1,2\n")
    with pytest.raises(UserInputError, match="unknown knob column\\(s\\) \\['fog'\\]"):
        load_schedule(bad, base, 1)
    rng = tmp_path / "range.csv"
    rng.write_text("fog_density\n150\n")
    with pytest.raises(UserInputError, match="row 1: knob 'fog_density' = 150.0 is out of range"):
        load_schedule(rng, base, 1)


# -- the closed loop -------------------------------------------------------------------------------------
def _stopping_lead(scene):
    """The same scene with a lead vehicle that stops at once and stays stopped."""
    vs = list(scene.vehicles)
    lead = next(i for i, v in enumerate(vs) if v.role == "lead")
    ap = dict(vs[lead].autopilot)
    ap["stop_rate"] = 6000.0  # per minute: it stops every time a stop ends
    vs[lead] = dataclasses.replace(vs[lead], autopilot=ap)
    return dataclasses.replace(scene, vehicles=tuple(vs))


@pytest.mark.render
def test_perception_matters_blind_hits_a_stopped_lead_and_oracle_stops(backend, highway_scenes) -> None:
    from genesis_rl.loop.drive import run_episode

    scene = _stopping_lead(highway_scenes.scene(1))
    clear = lambda _: Weather.default()  # noqa: E731
    blind = run_episode(backend, scene, load_system("blind"), clear, 300, seed=0, stop_on_collision=True)
    hit = [r for r in blind.records if r.collision.collided]
    assert hit and hit[0].collision.speed > 5.0
    oracle = run_episode(backend, scene, load_system("oracle"), clear, 300, seed=0)
    assert not any(r.collision.collided for r in oracle.records)
    assert min(r.ego.speed for r in oracle.records[-40:]) < 0.5  # it stopped behind the lead


@pytest.mark.render
def test_same_seed_same_episode(backend, highway_scenes) -> None:
    from genesis_rl.loop.drive import run_episode

    fog = lambda _: Weather.from_partial({"fog_density": 40.0})  # noqa: E731
    a = run_episode(backend, highway_scenes.scene(2), load_system("oracle"), fog, 60, seed=5)
    b = run_episode(backend, highway_scenes.scene(2), load_system("oracle"), fog, 60, seed=5)
    assert a.records == b.records


@pytest.mark.render
def test_drive_never_overwrites_a_result_without_force(tmp_path, capsys) -> None:
    from genesis_rl.commands.cli import main

    args = ["drive", "--map", "highway", "--scene", "0", "--system", "blind", "--steps", "3", "--out", str(tmp_path),
            "--quiet"]
    assert main(args) == 0
    from genesis_rl.core.files.manifest import MANIFEST
    from genesis_rl.core.files.output_folder import MARKER

    assert {p.name for p in tmp_path.iterdir()} == {"summary.json", "telemetry.parquet", "drive.gif", MARKER,
                                                     MANIFEST}  # the manifest lists the files --force may replace
    assert json.loads((tmp_path / MARKER).read_text())["kind"] == "drive"  # --force may replace it later
    (tmp_path / "summary.json").unlink()  # e.g. an interrupted earlier run left its telemetry
    before = (tmp_path / "telemetry.parquet").read_bytes()
    assert main(args) == 2
    assert "telemetry.parquet' already exists; pass --force" in capsys.readouterr().err
    assert (tmp_path / "telemetry.parquet").read_bytes() == before
    assert main([*args, "--force"]) == 0


def test_drive_threads_are_checked_and_only_set_for_the_run(tmp_path, capsys) -> None:
    import torch

    from genesis_rl.commands.cli import main

    before = torch.get_num_threads()
    assert main(["drive", "--threads", "0", "--out", str(tmp_path / "x")]) == 2
    assert "--threads = 0; allowed: an integer >= 1" in capsys.readouterr().err
    assert main(["drive", "--map", "highway", "--scene", "0", "--system", "blind", "--steps", "2", "--no-gif",
                 "--threads", "1", "--quiet", "--out", str(tmp_path / "y")]) == 0
    assert torch.get_num_threads() == before  # a notebook's or test's own setting survives the command


def test_schedule_files_as_spreadsheets_write_them(tmp_path) -> None:
    base = Weather.default()
    bom = tmp_path / "bom.csv"  # Excel's "CSV UTF-8" starts with a byte-order mark; a header may carry spaces
    bom.write_bytes("\ufeffstep, fog_density\r\n0,10\r\n1,20\r\n\r\n".encode())
    assert [w["fog_density"] for w in load_schedule(bom, base, 2)] == [10.0, 20.0]
    cases = {
        "step,fog_density,fog_density\n0,1,2\n": r"column\(s\) \['fog_density'\] appear more than once",
        "step,fog_density\n0,1,9\n": r"row 1 has 3 cells; the header has 2",
        "step,fog_density\n7,1\n": r"row 1: step = '7'; expected 0",
    }
    for i, (text, message) in enumerate(cases.items()):
        f = tmp_path / f"bad{i}.csv"
        f.write_text(text)
        with pytest.raises(UserInputError, match=message):
            load_schedule(f, base, 1)
    latin = tmp_path / "latin.csv"
    latin.write_bytes("step,fog_density\n0,1\xe9\n".encode("latin-1"))
    with pytest.raises(UserInputError, match="is not UTF-8 text"):
        load_schedule(latin, base, 1)


class _FixedRoute:
    """A route on given points: just what ``PolylineRoute.curvature_ahead`` reads."""

    def __init__(self, xy: np.ndarray) -> None:
        self.xy, self.index = xy, 0


def _arc(radius: float, length: float, vertex_every: float) -> np.ndarray:
    """Points every DS metres along a circular arc drawn as a polyline with a vertex every ``vertex_every`` m
    (0: the arc itself), as lite's highway lanes are."""
    from genesis_rl.sim.lite.maps.lane_graph import DS

    s = np.arange(0.0, length, DS)
    knots = np.arange(0.0, length + vertex_every, vertex_every) if vertex_every else s
    kx, ky = radius * np.sin(knots / radius), radius * (1 - np.cos(knots / radius))
    return np.column_stack([np.interp(s, knots, kx), np.interp(s, knots, ky)])


@pytest.mark.parametrize("vertex_every", [0.0, 2.0, 8.0])
def test_bend_curvature_is_the_roads_not_its_polyline_vertices(vertex_every) -> None:
    """The controller slows for bends by the curvature ahead. A 100 m bend drawn with a vertex every 8 m read
    as a 28 m one before 0.18 (the per-sample heading change smoothed over 2 m), slowing the highway profile
    to 11 m/s on a 25 m/s main line; now it reads within 15 % of 1/100, a smooth arc exactly, and a city
    corner (12 m radius between straights) within 10 %, so the ego still slows for it."""
    from genesis_rl.sim.route import PolylineRoute

    route = _FixedRoute(_arc(100.0, 200.0, vertex_every))
    kappa = PolylineRoute.curvature_ahead(route, 150.0)  # type: ignore[arg-type]
    assert kappa == pytest.approx(0.01, rel=0.15 if vertex_every else 0.01)
    run_up = np.column_stack([np.arange(-30.0, 0.0, 0.5), np.zeros(60)])
    # the arc ends at (12, 12), heading +y
    run_out = np.column_stack([np.full(60, 12.0), 12.0 + np.arange(0.5, 30.5, 0.5)])
    corner = np.vstack([run_up, _arc(12.0, 12.0 * math.pi / 2, vertex_every), run_out])
    assert 1.0 / PolylineRoute.curvature_ahead(_FixedRoute(corner), 80.0) == pytest.approx(12.0, rel=0.1)  # type: ignore[arg-type]
    straight = _FixedRoute(np.column_stack([np.arange(0.0, 200.0, 0.5), np.zeros(400)]))
    assert PolylineRoute.curvature_ahead(straight, 150.0) == 0.0  # type: ignore[arg-type]
