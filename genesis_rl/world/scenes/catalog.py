"""The scene catalog: a versioned JSON schema, validated on load with errors that name the field.

A scene is what the paper's Scenic generator produced: 30 vehicles (ego, lead ahead in the ego's lane,
neighbour front-right, 27 others within a radius), each with make, colour, pose on a lane and autopilot
parameters, plus the seed that drives the episode's randomness.

This module is the schema alone: it knows no backend. What a catalog must also satisfy on its backend (a
lite vehicle on its lane, no two overlapping at the start) is checked by that backend's scene module, which
:func:`genesis_rl.sim.backends.load_catalog` calls; load catalogs through it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import atomic_write_json
from genesis_rl.core.parsing import read_json
from genesis_rl.world.scenes.vehicles import MAKES

SCHEMA_NAME = "genesis-rl/scene-catalog"
SCHEMA_VERSION = 1
ROLES = ("ego", "lead", "neighbour", "other")


@dataclass(frozen=True)
class VehicleSpec:
    role: str
    make: str
    color_name: str
    color: tuple[float, float, float]
    lane: int
    s: float  # arc length along the lane [m]
    x: float
    y: float
    yaw: float  # [rad], CCW from +x
    speed: float  # initial speed [m/s]
    next_lane: int
    autopilot: dict[str, float] | None  # AutopilotParams fields; None for the ego


@dataclass(frozen=True)
class Scene:
    index: int
    map: str
    seed: int
    signal_offset: float  # [s] added to every junction's signal clock
    vehicles: tuple[VehicleSpec, ...]
    #: SHA-256 of the map's OpenDRIVE text where the backend's map names are not unique (CARLA names every
    #: generated world "OpenDriveMap"): the simulation checks the loaded map's content against it
    map_digest: str | None = None

    @property
    def ego(self) -> VehicleSpec:
        return self.vehicles[0]


@dataclass(frozen=True)
class Catalog:
    map: str
    seed: int
    backend: str
    scenes: tuple[Scene, ...]
    map_digest: str | None = None  # see Scene.map_digest; written only when set

    def to_json(self) -> dict[str, Any]:
        digest = {"map_digest": self.map_digest} if self.map_digest is not None else {}
        return {
            "schema": SCHEMA_NAME,
            "version": SCHEMA_VERSION,
            "backend": self.backend,
            "map": self.map,
            **digest,
            "seed": self.seed,
            "scenes": [
                {
                    "index": sc.index,
                    "map": sc.map,
                    "seed": sc.seed,
                    "signal_offset": sc.signal_offset,
                    "vehicles": [_vehicle_json(v) for v in sc.vehicles],
                }
                for sc in self.scenes
            ],
        }

    def save(self, path: Path) -> None:
        atomic_write_json(Path(path), self.to_json())

    def scene(self, index: int) -> Scene:
        if not 0 <= index < len(self.scenes):
            raise UserInputError(f"scene index {index} is out of range; "
                                 f"the catalog has scenes 0..{len(self.scenes) - 1}")
        return self.scenes[index]


_VEHICLE_FIELDS = tuple(f.name for f in fields(VehicleSpec))


def _vehicle_json(v: VehicleSpec) -> dict[str, Any]:
    """``dataclasses.asdict(v)``, the same keys in the same order, without its recursive deep copy (with it a
    36,000-vehicle catalog took 2.5x as long to save): the only mutable field, the autopilot, is copied by hand."""
    out = {name: getattr(v, name) for name in _VEHICLE_FIELDS}
    out["color"] = list(v.color)
    out["autopilot"] = None if v.autopilot is None else dict(v.autopilot)
    return out


_TYPE_NAMES = {str: "a string", int: "an integer", list: "a list", dict: "an object", float: "a number"}
#: autopilot fields (lite's AutopilotParams) and the physical range of each (docs/reliability.md)
AUTOPILOT_RANGES: dict[str, ranges.Ranged] = {
    "target_speed": ranges.SPEED,  # desired speed [m/s]
    "time_gap": ranges.Ranged(0.0, 10.0, "s"),  # IDM time headway
    "min_gap": ranges.Ranged(0.0, 100.0, "m"),  # IDM standstill gap
    "max_accel": ranges.ACCEL,  # IDM maximum acceleration
    "comfort_decel": ranges.Ranged(1e-3, 15.0, "m/s^2"),  # IDM comfortable deceleration
    "stop_rate": ranges.Ranged(0.0, 60.0, "stops/min"),  # spontaneous stops
    "speed_noise": ranges.Ranged(0.0, 10.0, "m/s"),  # std of the target speed's random walk
}
#: the least value each autopilot field may take (older name, kept for callers)
AUTOPILOT_MIN = {k: r.low for k, r in AUTOPILOT_RANGES.items()}
#: a lane index (lite) or key (CARLA: road id * 100 + lane id + 50), a scene index
LANE = ranges.Ranged(0, 2**31 - 1, integer=True)
INDEX = ranges.Ranged(0, 1_000_000_000, integer=True)


def _req(obj: Any, key: str, typ: type, where: str) -> Any:
    if not isinstance(obj, dict):
        raise UserInputError(f"catalog: '{where}' must be an object, got {type(obj).__name__}")
    if key not in obj:
        raise UserInputError(f"catalog: missing field '{where}.{key}'")
    value = obj[key]
    ok = isinstance(value, (int, float)) if typ is float else isinstance(value, typ)
    if not ok or (isinstance(value, bool) and typ is not bool):
        raise UserInputError(f"catalog: field '{where}.{key}' is {type(value).__name__} {value!r}, "
                             f"expected {_TYPE_NAMES.get(typ, typ.__name__)}")
    return value


def _number(obj: Any, key: str, where: str, rng: ranges.Ranged, role: str = "") -> Any:
    """A number in its physical range ``rng``: JSON's NaN and Infinity, 400-digit integers and absurd values
    (a speed of 1e200 m/s, an acceleration of 1e308 m/s^2) are refused here, before any arithmetic."""
    value = _req(obj, key, int if rng.integer else float, where)
    try:
        return rng.check(value, key)
    except UserInputError:
        pass
    unit = f" {rng.unit}" if rng.unit else ""
    shown = value if not isinstance(value, int) or abs(value) < 10**30 else f"{str(value)[:12]}..."
    if isinstance(value, float) and not math.isfinite(value):
        expected = f"a finite number in {rng.bounds()}{unit}"
    elif value < rng.low:
        expected = f"{'an integer ' if rng.integer else ''}>= {ranges.fmt(rng.low)}{unit}"
    else:
        expected = f"{'an integer ' if rng.integer else ''}<= {ranges.fmt(rng.high)}{unit}"
    whose = f" for the {role}" if role else ""
    raise UserInputError(f"catalog: field '{where}.{key}' = {shown}; expected {expected} "
                         f"(allowed{whose}: {rng.bounds()}{unit})")


def _autopilot(d: dict, role: str, where: str) -> dict[str, float] | None:
    ap = d.get("autopilot")
    if role == "ego":
        if ap is not None:
            raise UserInputError(f"catalog: '{where}.autopilot' must be null for the ego (the system drives it)")
        return None
    if not isinstance(ap, dict):
        raise UserInputError(f"catalog: '{where}.autopilot' must be an object with the fields "
                             f"{', '.join(AUTOPILOT_RANGES)}, got {type(ap).__name__}")
    unknown = sorted(set(ap) - set(AUTOPILOT_RANGES))
    if unknown:
        raise UserInputError(f"catalog: unknown field(s) {', '.join(repr(k) for k in unknown)} in "
                             f"'{where}.autopilot'; allowed: {', '.join(AUTOPILOT_RANGES)}")
    return {k: _number(ap, k, f"{where}.autopilot", rng, role) for k, rng in AUTOPILOT_RANGES.items()}


def _vehicle(d: Any, where: str) -> VehicleSpec:
    role = _req(d, "role", str, where)
    if role not in ROLES:
        raise UserInputError(f"catalog: '{where}.role' = '{role}'; allowed: {', '.join(ROLES)}")
    make = _req(d, "make", str, where)
    if make not in MAKES:
        raise UserInputError(f"catalog: '{where}.make' = '{make}'; allowed: {', '.join(MAKES)}")
    color = _req(d, "color", list, where)
    if len(color) != 3 or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and 0 <= c <= 1
                                  for c in color):
        raise UserInputError(f"catalog: '{where}.color' must be 3 numbers in 0..1, got {color}")
    lane, next_lane = _number(d, "lane", where, LANE, role), _number(d, "next_lane", where, LANE, role)
    s = _number(d, "s", where, ranges.ARC_LENGTH, role)
    x, y = _number(d, "x", where, ranges.COORDINATE, role), _number(d, "y", where, ranges.COORDINATE, role)
    yaw, speed = _number(d, "yaw", where, ranges.YAW, role), _number(d, "speed", where, ranges.SPEED, role)
    r, g, b = (float(c) for c in color)
    return VehicleSpec(role, make, _req(d, "color_name", str, where), (r, g, b), lane,
                       s, x, y, yaw, speed, next_lane, _autopilot(d, role, where))


def parse_catalog(data: Any) -> Catalog:
    """A catalog from its JSON data, checked against the schema (not against a backend's maps)."""
    if not isinstance(data, dict) or data.get("schema") != SCHEMA_NAME:
        raise UserInputError(f"not a scene catalog: field 'schema' must be '{SCHEMA_NAME}'")
    version = data.get("version")
    if type(version) is not int or version != SCHEMA_VERSION:  # not `!=` alone: JSON's true == 1 in Python
        raise UserInputError(f"catalog field 'version' = {version!r}; this genesis-rl reads version {SCHEMA_VERSION} "
                             "(an integer)")
    backend = _req(data, "backend", str, "catalog")
    map_name = _req(data, "map", str, "catalog")
    if not map_name:
        raise UserInputError("catalog field 'map' is empty; expected the map's name (e.g. urban, highway)")
    digest = data.get("map_digest")
    if digest is not None and not (isinstance(digest, str) and len(digest) == 64
                                   and all(c in "0123456789abcdef" for c in digest)):
        raise UserInputError(f"catalog field 'map_digest' = {digest!r}; allowed: the SHA-256 of the map's OpenDRIVE "
                             "as 64 lowercase hex digits, or no field")
    seed = _number(data, "seed", "catalog", ranges.SEED)
    scene_list = _req(data, "scenes", list, "catalog")
    if not scene_list:
        raise UserInputError("catalog field 'scenes' is empty: the catalog has no scenes")
    scenes = []
    for i, sd in enumerate(scene_list):
        where = f"scenes[{i}]"
        index = _number(sd, "index", where, INDEX)  # a subset (e.g. replay's one scene) keeps its scenes' indices
        scene_map = _req(sd, "map", str, where)
        if scene_map != map_name:
            raise UserInputError(f"catalog: '{where}.map' = '{scene_map}'; allowed: '{map_name}' (the catalog's map)")
        scene_seed = _number(sd, "seed", where, ranges.SEED)
        vehicles = tuple(_vehicle(v, f"{where}.vehicles[{j}]")
                         for j, v in enumerate(_req(sd, "vehicles", list, where)))
        if not vehicles or vehicles[0].role != "ego":
            raise UserInputError(f"catalog: '{where}.vehicles[0].role' must be 'ego'")
        egos = [j for j, v in enumerate(vehicles) if v.role == "ego"]
        if len(egos) > 1:
            raise UserInputError(f"catalog: '{where}.vehicles[{egos[1]}].role' = 'ego'; a scene has one ego, "
                                 f"vehicles[0]; allowed for the others: {', '.join(ROLES[1:])}")
        offset = _number(sd, "signal_offset", where, ranges.SIGNAL_OFFSET)
        scenes.append(Scene(index, scene_map, scene_seed, offset, vehicles, digest))
    return Catalog(map_name, seed, backend, tuple(scenes), digest)


def read_catalog(path: Path | str) -> Catalog:
    """The catalog in a JSON file, checked against the schema only (see :func:`parse_catalog`)."""
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"catalog '{path}' is a folder; expected a catalog file (.json)")
    if not path.is_file():
        raise UserInputError(f"catalog file '{path}' does not exist")
    from genesis_rl.core.parsing import CATALOG_MB

    return parse_catalog(read_json(path, "catalog file", CATALOG_MB))
