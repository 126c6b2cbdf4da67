"""The scene catalog: a versioned JSON schema, validated on load with errors that name the field.

A scene is what the paper's Scenic generator produced: 30 vehicles (ego, lead ahead in the ego's lane,
neighbour front-right, 27 others within a radius), each with make, colour, pose on a lane and autopilot
parameters, plus the seed that drives the episode's randomness.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from genesis_rl.errors import UserInputError
from genesis_rl.io_utils import atomic_write_json

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

    @property
    def ego(self) -> VehicleSpec:
        return self.vehicles[0]


@dataclass(frozen=True)
class Catalog:
    map: str
    seed: int
    backend: str
    scenes: tuple[Scene, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA_NAME,
            "version": SCHEMA_VERSION,
            "backend": self.backend,
            "map": self.map,
            "seed": self.seed,
            "scenes": [
                {
                    "index": sc.index,
                    "map": sc.map,
                    "seed": sc.seed,
                    "signal_offset": sc.signal_offset,
                    "vehicles": [asdict(v) for v in sc.vehicles],
                }
                for sc in self.scenes
            ],
        }

    def save(self, path: Path) -> None:
        atomic_write_json(Path(path), self.to_json())

    def scene(self, index: int) -> Scene:
        if not 0 <= index < len(self.scenes):
            raise UserInputError(f"scene index {index} out of range; the catalog has scenes 0..{len(self.scenes) - 1}")
        return self.scenes[index]


def _req(obj: dict, key: str, typ: type | tuple[type, ...], where: str) -> Any:
    if not isinstance(obj, dict) or key not in obj:
        raise UserInputError(f"catalog: missing field '{where}.{key}'")
    value = obj[key]
    if typ is float:
        typ = (int, float)
    if not isinstance(value, typ) or isinstance(value, bool) and typ is not bool:
        raise UserInputError(f"catalog: field '{where}.{key}' has type {type(value).__name__}, expected {typ}")
    return value


def _vehicle(d: dict, where: str, map_lanes: int | None) -> VehicleSpec:
    from genesis_rl.lite.vehicles import MAKES

    role = _req(d, "role", str, where)
    if role not in ROLES:
        raise UserInputError(f"catalog: '{where}.role' = '{role}'; allowed: {', '.join(ROLES)}")
    make = _req(d, "make", str, where)
    if make not in MAKES:
        raise UserInputError(f"catalog: '{where}.make' = '{make}'; allowed: {', '.join(MAKES)}")
    color = _req(d, "color", list, where)
    if len(color) != 3 or not all(isinstance(c, (int, float)) and 0 <= c <= 1 for c in color):
        raise UserInputError(f"catalog: '{where}.color' must be 3 numbers in 0..1, got {color}")
    lane = _req(d, "lane", int, where)
    next_lane = _req(d, "next_lane", int, where)
    if map_lanes is not None and not (0 <= lane < map_lanes and 0 <= next_lane < map_lanes):
        raise UserInputError(f"catalog: '{where}.lane'/'next_lane' out of the map's lanes 0..{map_lanes - 1}")
    ap = d.get("autopilot")
    if ap is not None and not isinstance(ap, dict):
        raise UserInputError(f"catalog: '{where}.autopilot' must be an object or null")
    return VehicleSpec(
        role, make, _req(d, "color_name", str, where), tuple(float(c) for c in color), lane,
        float(_req(d, "s", float, where)), float(_req(d, "x", float, where)), float(_req(d, "y", float, where)),
        float(_req(d, "yaw", float, where)), float(_req(d, "speed", float, where)), next_lane,
        {k: float(v) for k, v in ap.items()} if ap else None,
    )


def catalog_from_json(data: Any, check_map: bool = True) -> Catalog:
    if not isinstance(data, dict) or data.get("schema") != SCHEMA_NAME:
        raise UserInputError(f"not a scene catalog: field 'schema' must be '{SCHEMA_NAME}'")
    version = data.get("version")
    if version != SCHEMA_VERSION:
        raise UserInputError(f"catalog field 'version' = {version!r}; this genesis-rl reads version {SCHEMA_VERSION}")
    backend = _req(data, "backend", str, "catalog")
    map_name = _req(data, "map", str, "catalog")
    map_lanes = None
    if backend == "lite" and check_map:
        from genesis_rl.lite.maps import load_map

        map_lanes = len(load_map(map_name).lanes)
    scenes = []
    for i, sd in enumerate(_req(data, "scenes", list, "catalog")):
        where = f"scenes[{i}]"
        vehicles = tuple(_vehicle(v, f"{where}.vehicles[{j}]", map_lanes)
                         for j, v in enumerate(_req(sd, "vehicles", list, where)))
        if not vehicles or vehicles[0].role != "ego":
            raise UserInputError(f"catalog: '{where}.vehicles[0].role' must be 'ego'")
        scenes.append(Scene(_req(sd, "index", int, where), _req(sd, "map", str, where), _req(sd, "seed", int, where),
                            float(_req(sd, "signal_offset", float, where)), vehicles))
    return Catalog(map_name, _req(data, "seed", int, "catalog"), backend, tuple(scenes))


def load_catalog(path: Path | str) -> Catalog:
    path = Path(path)
    if not path.is_file():
        raise UserInputError(f"catalog file '{path}' does not exist")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserInputError(f"catalog file '{path}' is not valid JSON: {err}") from None
    return catalog_from_json(data)
