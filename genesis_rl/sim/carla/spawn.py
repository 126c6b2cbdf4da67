"""A catalog scene -> what to spawn on a CARLA map: blueprint candidates by make, colour, transform, speed.

The catalog is backend-neutral: makes are the lite classes (sedan ... bus), poses are in our right-handed
frame. Each vehicle is snapped to the nearest driving lane of the ``carla.Map`` (its centre line and
heading), lifted a little so it does not spawn into the road, and gets a blueprint of its class from the
server's library. :func:`plan_scene` is pure (works on an offline ``carla.Map``); :func:`spawn_commands`
needs the server's blueprint library.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.carla._carla import require_carla
from genesis_rl.sim.carla.frames import transform_to_carla
from genesis_rl.sim.carla.lanes import lane_from_key
from genesis_rl.world.scenes.catalog import Scene

#: CARLA 0.9.16 vehicle blueprints per catalog make, most typical first. Missing ones (other releases,
#: trimmed packages) are skipped; when none is left, any 4-wheeled vehicle of the right ``base_type`` is used.
BLUEPRINTS: dict[str, tuple[str, ...]] = {
    "sedan": ("vehicle.tesla.model3", "vehicle.lincoln.mkz_2020", "vehicle.toyota.prius", "vehicle.audi.a2",
              "vehicle.dodge.charger_2020", "vehicle.mercedes.coupe_2020", "vehicle.seat.leon",
              "vehicle.chevrolet.impala", "vehicle.ford.crown"),
    "hatchback": ("vehicle.mini.cooper_s_2021", "vehicle.citroen.c3", "vehicle.nissan.micra", "vehicle.audi.a2",
                  "vehicle.micro.microlino"),
    "suv": ("vehicle.audi.etron", "vehicle.nissan.patrol_2021", "vehicle.jeep.wrangler_rubicon",
            "vehicle.mercedes.sprinter", "vehicle.bmw.grandtourer"),
    "van": ("vehicle.volkswagen.t2_2021", "vehicle.mercedes.sprinter", "vehicle.ford.ambulance"),
    "truck": ("vehicle.carlamotors.european_hgv", "vehicle.carlamotors.carlacola", "vehicle.tesla.cybertruck",
              "vehicle.carlamotors.firetruck"),
    "bus": ("vehicle.mitsubishi.fusorosa",),
}
#: CARLA's ``base_type`` attribute for the fallback choice
BASE_TYPES: dict[str, str] = {"sedan": "car", "hatchback": "car", "suv": "car", "van": "van", "truck": "truck",
                              "bus": "bus"}
SPAWN_LIFT = 0.3  # [m] above the lane so the chassis does not start inside the road mesh
MAX_SNAP = 3.0  # [m] a catalog pose farther than this from every driving lane is an error


@dataclass(frozen=True)
class SpawnSpec:
    """One vehicle to spawn: ``index`` is its position in the scene (its ``vehicle_id``)."""

    index: int
    role: str
    make: str
    blueprint_ids: tuple[str, ...]
    color: str  # CARLA's colour attribute, "R,G,B" in 0..255
    transform: Any  # carla.Transform
    speed: float  # [m/s] initial, along the lane
    autopilot: dict[str, float] | None

    @property
    def role_name(self) -> str:
        """CARLA's ``role_name`` attribute: ``hero`` marks the ego for tools such as the spectator."""
        return "hero" if self.role == "ego" else f"genesis_{self.role}_{self.index}"


def color_attribute(color: tuple[float, float, float]) -> str:
    """sRGB in 0..1 -> CARLA's "R,G,B" in 0..255."""
    return ",".join(str(int(round(min(max(c, 0.0), 1.0) * 255))) for c in color)


def snap_to_lane(carla_map: Any, x: float, y: float, yaw: float, lane: int | None = None,
                 s: float | None = None) -> Any:
    """The driving-lane waypoint of a catalog pose (our frame), or None when none is within ``MAX_SNAP``.

    A catalog written by the CARLA generator also names the OpenDRIVE (road, lane, s) of the pose: that
    waypoint is exact and is used when it agrees with (x, y); otherwise the nearest lane point is taken."""
    carla = require_carla()
    loc = transform_to_carla(x, y, 0.0, yaw).location

    def planar(wp: Any) -> float:
        w = wp.transform.location
        return math.hypot(w.x - loc.x, w.y - loc.y)

    if lane is not None and s is not None:
        road_id, lane_id = lane_from_key(lane)
        wp = carla_map.get_waypoint_xodr(road_id, lane_id, float(s)) if lane_id != 0 else None
        if wp is not None and wp.lane_type == carla.LaneType.Driving and planar(wp) < 0.5:
            return wp
    wp = carla_map.get_waypoint(loc, project_to_road=True, lane_type=carla.LaneType.Driving)
    return wp if wp is not None and planar(wp) <= MAX_SNAP else None


def plan_scene(scene: Scene, carla_map: Any) -> list[SpawnSpec]:
    """Spawn specs of every vehicle of ``scene``, snapped to lanes of ``carla_map`` (ego first)."""
    carla = require_carla()
    specs = []
    for i, v in enumerate(scene.vehicles):
        wp = snap_to_lane(carla_map, v.x, v.y, v.yaw, v.lane, v.s)
        if wp is None:
            raise UserInputError(
                f"scene {scene.index} vehicle {i} ({v.role}) at x={v.x:.1f}, y={v.y:.1f} is more than {MAX_SNAP:g} m "
                f"from every driving lane of CARLA map '{scene.map}': was the catalog generated for this map? "
                f"(genesis-rl scenes --backend carla --map {scene.map} ...)"
            )
        if v.make not in BLUEPRINTS:
            raise UserInputError(f"scene {scene.index} vehicle {i}: make '{v.make}' has no CARLA blueprints; "
                                 f"allowed: {', '.join(BLUEPRINTS)}")
        tf = wp.transform
        transform = carla.Transform(carla.Location(tf.location.x, tf.location.y, tf.location.z + SPAWN_LIFT),
                                    carla.Rotation(pitch=tf.rotation.pitch, yaw=tf.rotation.yaw, roll=0.0))
        specs.append(SpawnSpec(i, v.role, v.make, BLUEPRINTS[v.make], color_attribute(v.color), transform,
                               float(v.speed), v.autopilot))
    return specs


def choose_blueprint(spec: SpawnSpec, library: Any, rng: np.random.Generator) -> Any:
    """A blueprint for ``spec`` from the server's library, its colour and role name set."""
    present = [bid for bid in spec.blueprint_ids if library.filter(bid)]
    if present:
        bp = library.find(present[int(rng.integers(len(present)))])
    else:
        base = BASE_TYPES[spec.make]
        pool = sorted((b for b in library.filter("vehicle.*")
                       if b.has_attribute("number_of_wheels") and int(b.get_attribute("number_of_wheels")) == 4
                       and (not b.has_attribute("base_type") or b.get_attribute("base_type").as_str().lower() == base)),
                      key=lambda b: b.id)
        if not pool:
            raise UserInputError(f"the CARLA server has no 4-wheeled vehicle blueprint for make '{spec.make}'")
        bp = pool[int(rng.integers(len(pool)))]
    if bp.has_attribute("color") and bp.get_attribute("color").is_modifiable:
        bp.set_attribute("color", spec.color)
    if bp.has_attribute("role_name"):
        bp.set_attribute("role_name", spec.role_name)
    return bp


def spawn_commands(specs: list[SpawnSpec], library: Any, tm_port: int, seed: int) -> list[Any]:
    """``SpawnActor`` commands (NPCs chained with ``SetAutopilot`` on the traffic manager at ``tm_port``),
    in the order of ``specs``; blueprint choices are drawn from ``seed``."""
    carla = require_carla()
    rng = np.random.default_rng(seed)
    cmds = []
    for spec in specs:
        cmd = carla.command.SpawnActor(choose_blueprint(spec, library, rng), spec.transform)
        if spec.autopilot is not None:
            cmd = cmd.then(carla.command.SetAutopilot(carla.command.FutureActor, True, int(tm_port)))
        cmds.append(cmd)
    return cmds


def initial_velocity(spec: SpawnSpec) -> Any:
    """The spec's initial speed along its heading, as a ``carla.Vector3D`` (CARLA frame)."""
    carla = require_carla()
    yaw = math.radians(spec.transform.rotation.yaw)
    return carla.Vector3D(spec.speed * math.cos(yaw), spec.speed * math.sin(yaw), 0.0)
