"""Scenes from the paper's generator, Scenic 3: ``genesis-rl scenes --generator scenic``.

The shipped program (``scenic_scenes/initial_scene.scenic``) places the ego, the lead, the neighbour and
candidates for the others on an OpenDRIVE map, with makes and colours from our vocabulary. This module runs
it and writes the result in the catalog schema every backend reads:

- on a lite map, Scenic reads the map's OpenDRIVE export (:mod:`genesis_rl.sim.lite.maps.opendrive`); each car
  is snapped to the nearest lite lane sample with its heading (lite places vehicles by lane and s);
- on a CARLA map, Scenic reads the map's OpenDRIVE (``carla.Map.to_opendrive()``: a server's town, or any
  ``carla.Map``) and each car is snapped to its CARLA waypoint, as the CARLA generator writes it.

The others are taken in Scenic's order while they fit (no overlap, a safe headway on lite), until the scene
holds 30 vehicles; a draw with too few is replaced by Scenic's next one. Speeds and autopilot settings come
from the scene's own generator, as in the built-in generators. Every draw flows from the catalog seed:
scene i seeds Python's and numpy's global generators (which Scenic samples from) with its own seed, and
restores them afterwards.
"""

from __future__ import annotations

import math
import random
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from genesis_rl.core.errors import UserInputError
from genesis_rl.world.scenes.catalog import Catalog, Scene, VehicleSpec
from genesis_rl.world.scenes.vehicles import MAKES, PALETTE

PROGRAM = Path(__file__).parent / "initial_scene.scenic"
N_VEHICLES = 30
CANDIDATES = 80  # Scenic's candidates for the 27 others
RADIUS = 90.0  # [m]
MAX_DRAWS = 50  # Scenic scenes tried for one catalog scene
EGO_MAKES = ("sedan", "hatchback", "suv")

#: (x, y, yaw, role, make, colour, rng) -> a vehicle on the map, or None where none can stand
Snap = Callable[[float, float, float, str, str, str, np.random.Generator], VehicleSpec | None]


def require_scenic() -> Any:
    try:
        import scenic
    except ImportError as err:
        raise UserInputError(f"--generator scenic needs Scenic 3: pip install -e .[scenic] ({err})") from None
    return scenic


def compile_program(xodr_path: Path, candidates: int = CANDIDATES, radius: float = RADIUS) -> Any:
    """The shipped Scenic program on the OpenDRIVE map at ``xodr_path``."""
    scenic = require_scenic()
    names = list(MAKES)
    params = {"map": str(xodr_path), "others": int(candidates), "radius": float(radius), "makes": names,
              "make_weights": [float(MAKES[n].weight) for n in names], "ego_makes": list(EGO_MAKES),
              "colors": list(PALETTE)}
    return scenic.scenarioFromFile(str(PROGRAM), params=params, model="scenic.domains.driving.model", mode2D=True)


@contextmanager
def _seeded(seed: int) -> Iterator[None]:
    """Python's and numpy's global generators seeded for one Scenic draw, restored afterwards."""
    # Scenic samples from the legacy global generators, so they are what must be seeded here
    py_state, np_state = random.getstate(), np.random.get_state()  # noqa: NPY002
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002
    try:
        yield
    finally:
        random.setstate(py_state)
        np.random.set_state(np_state)  # noqa: NPY002


def _objects(scene: Any) -> list[tuple[float, float, float, str, str, str]]:
    """(x, y, yaw CCW from +x, role, make, colour) of each Scenic object (Scenic's yaw is from +y)."""
    return [(float(o.position.x), float(o.position.y), float(o.heading) + math.pi / 2.0, str(o.genesis_role),
             str(o.genesis_make), str(o.genesis_color)) for o in scene.objects]


def _place(objects: list[tuple[float, float, float, str, str, str]], snap: Snap, fits: Callable[..., bool],
           rng: np.random.Generator) -> list[VehicleSpec] | None:
    placed: list[VehicleSpec] = []
    for x, y, yaw, role, make, color in objects:
        if len(placed) >= N_VEHICLES:
            break
        spec = snap(x, y, yaw, role, make, color, rng)
        ok = spec is not None and fits(spec, placed)
        if role != "other" and not ok:
            return None  # the ego, the lead and the neighbour must all stand
        if ok and spec is not None:
            placed.append(spec)
    return placed if len(placed) >= N_VEHICLES else None


def iter_scenes(scenario: Any, map_name: str, count: int, seed: int, snap: Snap, fits: Callable[..., bool],
                signal_cycle: float | None) -> Iterator[Scene]:
    """Scenes 0..count-1; scene i depends only on (map, seed, i). ``signal_cycle`` None: the signal offset is
    0 (CARLA runs its own lights)."""
    for i, ss in enumerate(np.random.SeedSequence(seed).spawn(count)):
        scene_seed = int(ss.generate_state(1)[0])
        rng = np.random.default_rng(scene_seed)
        for _ in range(MAX_DRAWS):
            with _seeded(int(rng.integers(2**31))):
                drawn, _ = scenario.generate(maxIterations=2000, verbosity=0)
            placed = _place(_objects(drawn), snap, fits, rng)
            if placed is not None:
                break
        else:
            raise RuntimeError(f"scene {i}: {MAX_DRAWS} Scenic scenes on {map_name} left fewer than {N_VEHICLES} "
                               "vehicles that fit")
        sim_seed = int(rng.integers(2**31))
        offset = 0.0 if signal_cycle is None else float(rng.uniform(0.0, signal_cycle))
        yield Scene(i, map_name, sim_seed, offset, tuple(placed))


def _catalog(xodr_text: str, backend: str, map_name: str, count: int, seed: int, snap: Snap,
             fits: Callable[..., bool], signal_cycle: float | None, progress: bool) -> Catalog:
    """Run the shipped program on the OpenDRIVE ``xodr_text`` (written to a temporary file for Scenic)."""
    with tempfile.TemporaryDirectory(prefix="genesis-scenic-") as tmp:
        xodr = Path(tmp) / f"{map_name}.xodr"
        xodr.write_text(xodr_text)
        scenario = compile_program(xodr)
        scenes: Iterator[Scene] = iter_scenes(scenario, map_name, count, seed, snap, fits, signal_cycle)
        if progress:
            scenes = tqdm(scenes, total=count, desc=f"scenic {map_name}", unit="scene")
        return Catalog(map_name, seed, backend, tuple(scenes))


# -- lite maps -------------------------------------------------------------------------------------------------
def lite_snap(road_map: Any) -> Snap:
    from genesis_rl.sim.lite.maps.lane_graph import DS
    from genesis_rl.sim.lite.scenes import draw_autopilot

    def snap(x: float, y: float, yaw: float, role: str, make: str, color: str,
             rng: np.random.Generator) -> VehicleSpec | None:
        k = road_map.nearest_lane_point(x, y, yaw)
        if k < 0:
            return None
        lane = int(road_map.point_lane[k])
        s = (k - int(road_map.offset[lane])) * DS
        if role == "other" and (road_map.lanes[lane].road < 0 or not 3.0 <= s <= road_map.length[lane] - 3.0):
            return None  # others start on roads, clear of the lane's ends (as the built-in generator's)
        px, py, _, pyaw = road_map.pose(lane, s)
        limit = road_map.speed_limit(lane)
        speed = float(rng.uniform(0.5, 0.9) if role != "other" else rng.uniform(0.0, 0.9))
        succ = road_map.lanes[lane].successors
        ap = None if role == "ego" else draw_autopilot(rng, limit, role)
        return VehicleSpec(role, make, color, PALETTE[color], lane, float(s), px, py, pyaw, float(limit * speed),
                           int(succ[int(rng.integers(len(succ)))]), ap)

    return snap


def lite_catalog(map_name: str, count: int, seed: int, progress: bool = False) -> Catalog:
    """``count`` Scenic scenes on the lite map ``map_name`` (through its OpenDRIVE export)."""
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive
    from genesis_rl.sim.lite.scenes import _safe_headway, check_map, fits

    check_map(map_name, "--map")
    road_map = load_map(map_name)

    def fit(spec: VehicleSpec, placed: list[VehicleSpec]) -> bool:
        return fits(spec, placed) and (spec.role != "other" or _safe_headway(spec, placed))

    return _catalog(to_opendrive(road_map), "lite", map_name, count, seed, lite_snap(road_map), fit,
                    road_map.timing.cycle, progress)


# -- CARLA maps ------------------------------------------------------------------------------------------------
def carla_snap(carla_map: Any) -> Snap:
    from genesis_rl.sim.carla._carla import require_carla
    from genesis_rl.sim.carla.frames import pose_from_carla
    from genesis_rl.sim.carla.lanes import lane_key
    from genesis_rl.sim.carla.scenes import SPEED_LIMIT
    from genesis_rl.sim.lite.scenes import draw_autopilot

    carla = require_carla()

    def snap(x: float, y: float, yaw: float, role: str, make: str, color: str,
             rng: np.random.Generator) -> VehicleSpec | None:
        wp = carla_map.get_waypoint(carla.Location(x, -y, 0.0), project_to_road=True, lane_type=carla.LaneType.Driving)
        if wp is None or math.cos(-math.radians(wp.transform.rotation.yaw) - yaw) < 0.5:
            return None  # no lane there going the car's way
        if role == "other" and wp.is_junction:
            return None
        px, py, _, pyaw, _ = pose_from_carla(wp.transform)
        key = lane_key(wp.road_id, wp.lane_id)
        speed = float(rng.uniform(0.5, 0.9) if role != "other" else rng.uniform(0.0, 0.9))
        ap = None if role == "ego" else draw_autopilot(rng, SPEED_LIMIT, role)
        return VehicleSpec(role, make, color, PALETTE[color], key, float(wp.s), px, py, pyaw, SPEED_LIMIT * speed, key,
                           ap)

    return snap


def carla_catalog(carla_map: Any, map_name: str, count: int, seed: int, progress: bool = False) -> Catalog:
    """``count`` Scenic scenes on a ``carla.Map`` (a server's town, or one built from OpenDRIVE text)."""
    from genesis_rl.sim.carla.scenes import CARLA_FIT_RADIUS
    from genesis_rl.sim.lite.scenes import fits

    return _catalog(carla_map.to_opendrive(), "carla", map_name, count, seed, carla_snap(carla_map),
                    lambda spec, placed: fits(spec, placed, CARLA_FIT_RADIUS), None, progress)  # CARLA runs its lights


def carla_catalog_from_server(map_name: str, count: int, seed: int, settings: Any, progress: bool = False) -> Catalog:
    """Load ``map_name`` on the server that ``settings`` name and generate on its map."""
    from genesis_rl.sim.carla.backend import CarlaBackend

    backend = CarlaBackend(settings.host, settings.port, settings.timeout)
    try:
        carla_map = backend.map_of(backend.load_map(map_name))
        return carla_catalog(carla_map, map_name, count, seed, progress)
    finally:
        backend.close()
