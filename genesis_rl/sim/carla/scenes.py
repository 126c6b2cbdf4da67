"""Scene generation on CARLA maps, into the same catalog schema as the lite generator.

As the paper's Scenic program: the ego on a spawn point of a lane that has a same-direction lane to its
right, a lead ahead in the ego's lane, a neighbour ahead in the lane to the right, the rest on driving lanes
within a radius of the ego, none overlapping. Makes and colours come from the catalog's vocabulary
(:mod:`genesis_rl.world.scenes.vehicles`), so the catalog loader validates CARLA catalogs as it does lite ones.

The selection works on a ``carla.Map`` alone (so it is tested offline on a map built from an OpenDRIVE
string); :func:`generate_catalog_from_server` takes the map and its spawn points from a running server.
Catalog fields on CARLA: ``lane`` is :func:`lane_key` of (road id, lane id), ``s`` the OpenDRIVE s of the
spawn waypoint, ``next_lane`` equals ``lane`` (the traffic manager routes NPCs at junctions), poses are in
our right-handed frame (y and yaw are CARLA's negated), ``signal_offset`` is 0 (CARLA runs its own lights).

The module-level :func:`check_map`, :func:`default_count`, :func:`generate` and :func:`check_catalog` are the
CARLA backend's scene source (:class:`genesis_rl.sim.backends.SceneSource`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.carla._carla import require_carla
from genesis_rl.sim.carla.backend import CarlaBackend
from genesis_rl.sim.carla.frames import pose_from_carla
from genesis_rl.sim.carla.identity import opendrive_digest
from genesis_rl.sim.carla.lanes import lane_key
from genesis_rl.sim.interface import ConnectionSettings
from genesis_rl.world.scenes.catalog import Catalog, Scene, VehicleSpec
from genesis_rl.world.scenes.placement import draw_autopilot, draw_make, fits
from genesis_rl.world.scenes.vehicles import PALETTE

#: the paper's catalog sizes on CARLA: Town10 (train) 1202 scenes, Town05 (test) 1199
DEFAULT_COUNTS = {"Town10HD_Opt": 1202, "Town10HD": 1202, "Town05": 1199, "Town05_Opt": 1199}
N_VEHICLES = 30
RADIUS = 90.0  # [m] others within this distance of the ego
GRID = 5.0  # [m] spacing of the candidate waypoints for others
SPEED_LIMIT = 30.0 / 3.6  # [m/s] CARLA's default urban limit; initial speeds and NPC targets scale with it
CARLA_FIT_RADIUS = 20.0  # [m] vehicles checked for overlap when placing one (wider lanes, junctions than lite)


def _driving(wp: Any) -> bool:
    carla = require_carla()
    return wp is not None and wp.lane_type == carla.LaneType.Driving


def _right_neighbour(wp: Any) -> Any:
    """The lane to the right going the same way (same sign of lane id), or None."""
    r = wp.get_right_lane()
    return r if _driving(r) and r.lane_id * wp.lane_id > 0 else None


def ego_candidates(carla_map: Any, spawn_points: Sequence[Any] | None = None) -> list[Any]:
    """Waypoints where an ego may start: the server's spawn points on driving lanes (an offline map has
    none: then lane points every 10 m outside junctions)."""
    carla = require_carla()
    if spawn_points:
        wps = [carla_map.get_waypoint(tf.location, project_to_road=True, lane_type=carla.LaneType.Driving)
               for tf in spawn_points]
    else:
        wps = [w for w in carla_map.generate_waypoints(10.0) if not w.is_junction]
    return [w for w in wps if _driving(w)]


def _vehicle(rng: np.random.Generator, wp: Any, role: str, make: str, speed_frac: float) -> VehicleSpec:
    x, y, _, yaw, _ = pose_from_carla(wp.transform)
    key = lane_key(wp.road_id, wp.lane_id)
    color_name = str(rng.choice(list(PALETTE)))
    autopilot = None if role == "ego" else draw_autopilot(rng, SPEED_LIMIT, role)
    return VehicleSpec(role, make, color_name, PALETTE[color_name], key, float(wp.s), x, y, yaw,
                       float(SPEED_LIMIT * speed_frac), key, autopilot)


def _ahead(rng: np.random.Generator, wp: Any, distance: float) -> Any:
    nxt = wp.next(distance)
    return nxt[int(rng.integers(len(nxt)))] if nxt else None


def generate_scene(carla_map: Any, map_name: str, egos: Sequence[Any], pool: Sequence[Any], index: int, seed: int,
                   n_vehicles: int = N_VEHICLES, radius: float = RADIUS, map_digest: str | None = None) -> Scene:
    """One scene: ``egos`` are the ego's candidate waypoints, ``pool`` the candidates for the others."""
    rng = np.random.default_rng(seed)
    with_right = [w for w in egos if _right_neighbour(w) is not None]
    if not with_right:
        raise UserInputError(f"CARLA map '{map_name}' has no spawn point with a same-direction lane to its right "
                             "(the neighbour's place)")
    for _ in range(1000):
        w_ego = with_right[int(rng.integers(len(with_right)))]
        w_lead = _ahead(rng, w_ego, float(rng.uniform(15.0, 40.0)))
        w_nb = _ahead(rng, _right_neighbour(w_ego), float(rng.uniform(6.0, 20.0)))
        if w_lead is None or w_nb is None or not _driving(w_lead) or not _driving(w_nb):
            continue
        speed = float(rng.uniform(0.5, 0.9))
        ego = _vehicle(rng, w_ego, "ego", str(rng.choice(["sedan", "hatchback", "suv"])), speed)
        lead = _vehicle(rng, w_lead, "lead", draw_make(rng), speed)
        neighbour = _vehicle(rng, w_nb, "neighbour", draw_make(rng), speed)
        if fits(lead, [ego], CARLA_FIT_RADIUS) and fits(neighbour, [ego, lead], CARLA_FIT_RADIUS):
            placed = [ego, lead, neighbour]
            break
    else:
        raise RuntimeError(f"scene {index}: found no ego position with room for the lead and the neighbour")
    loc = w_ego.transform.location
    near = [w for w in pool if (w.transform.location.x - loc.x) ** 2 + (w.transform.location.y - loc.y) ** 2
            < radius**2]
    order = rng.permutation(len(near))
    for k in order:
        if len(placed) >= n_vehicles:
            break
        spec = _vehicle(rng, near[int(k)], "other", draw_make(rng), float(rng.uniform(0.0, 0.9)))
        if fits(spec, placed, CARLA_FIT_RADIUS):
            placed.append(spec)
    if len(placed) < n_vehicles:
        raise RuntimeError(f"scene {index}: could only place {len(placed)} of {n_vehicles} vehicles within "
                           f"{radius:g} m of the ego on {map_name}")
    return Scene(index, map_name, int(rng.integers(2**31)), 0.0, tuple(placed), map_digest)


def iter_scenes(carla_map: Any, map_name: str, count: int, seed: int, spawn_points: Sequence[Any] | None = None,
                n_vehicles: int = N_VEHICLES, radius: float = RADIUS) -> Iterator[Scene]:
    """Scenes 0..count-1; scene i depends only on (map, seed, i), as in the lite generator."""
    egos = ego_candidates(carla_map, spawn_points)
    pool = [w for w in carla_map.generate_waypoints(GRID) if _driving(w)]
    digest = opendrive_digest(carla_map.to_opendrive())
    for i, ss in enumerate(np.random.SeedSequence(seed).spawn(count)):
        yield generate_scene(carla_map, map_name, egos, pool, i, int(ss.generate_state(1)[0]), n_vehicles, radius,
                             digest)


def generate_catalog(carla_map: Any, map_name: str, count: int, seed: int, spawn_points: Sequence[Any] | None = None,
                     n_vehicles: int = N_VEHICLES, progress: bool = False) -> Catalog:
    """A catalog of ``count`` scenes on ``carla_map`` (offline or a server's), with the digest of its
    OpenDRIVE (:mod:`~genesis_rl.sim.carla.identity`): episodes check that the server runs this map."""
    scenes: Iterator[Scene] = iter_scenes(carla_map, map_name, count, seed, spawn_points, n_vehicles)
    if progress:
        scenes = tqdm(scenes, total=count, desc=f"scenes {map_name}", unit="scene")
    made = tuple(scenes)
    return Catalog(map_name, seed, "carla", made, made[0].map_digest if made else None)


def generate_catalog_from_server(map_name: str, count: int, seed: int, *, host: str = "localhost", port: int = 2000,
                                 timeout: float = 10.0, progress: bool = False) -> Catalog:
    """Load ``map_name`` on the server at host:port and generate from its map and spawn points (the map
    stays loaded: episodes on it start faster)."""
    backend = CarlaBackend(host, port, timeout)
    try:
        world = backend.load_map(map_name)
        carla_map = backend.map_of(world)
        spawn_points = backend.call("reading spawn points", carla_map.get_spawn_points)
        return generate_catalog(carla_map, map_name, count, seed, spawn_points, progress=progress)
    finally:
        backend.close()


# -- the scene source of the CARLA backend (genesis_rl.sim.backends.SceneSource) --------------------------------
def check_map(map_name: str, field: str) -> None:
    """Nothing to check offline: the server says which maps it has when the catalog is generated."""


def default_count(map_name: str) -> int:
    """The paper's size for Town10 and Town05 (see :data:`DEFAULT_COUNTS`), else 50."""
    return DEFAULT_COUNTS.get(map_name, 50)


def generate(map_name: str, count: int, seed: int, settings: ConnectionSettings, progress: bool = False) -> Catalog:
    """``count`` scenes on ``map_name``, generated on the server that ``settings`` name."""
    return generate_catalog_from_server(map_name, count, seed, host=settings.host, port=settings.port,
                                        timeout=settings.timeout, progress=progress)


def check_catalog(catalog: Catalog) -> None:
    """Nothing beyond the schema offline: poses are snapped to the server's lanes when spawned, and a pose
    far from every lane fails there (:func:`genesis_rl.sim.carla.spawn.plan_scene`)."""
