"""An OpenSCENARIO file read back with scenariogeneration's reader into what lite needs to drive it.

The file is parsed by ``scenariogeneration.xosc.ParseOpenScenario`` (so what we read is what a third-party
reader understood of it), and the parsed scenario's element tree is then read by name: entities, their start
(Init: ``TeleportAction`` to a ``WorldPosition``, ``AbsoluteSpeedAction``), each vehicle's
``FollowTrajectoryAction`` polyline, and the weather events that :mod:`writer` writes.
"""

from __future__ import annotations

import contextlib
import io
import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.exports.openscenario.environment import OscEnvironment
from genesis_rl.exports.openscenario.schema import require_scenariogeneration, scenario_minor_version
from genesis_rl.exports.openscenario.writer import (
    BRAKE_LIGHTS_COMMAND,
    EGO_NAME,
    KNOBS_COMMAND,
    START_KNOBS_EVENT,
    STEP_WEATHER_EVENT,
)

POSE_FIELDS = ("x", "y", "z", "h", "p")


@dataclass(frozen=True)
class ParsedVehicle:
    """A vehicle of the file: name, CARLA blueprint, box [m], properties, start pose (reference point: rear
    axle centre; x, y, z, h, p as written) and speed, its trajectory (times [s], poses) if it has one, and
    its brake-light switches (fired once simulation time exceeds the time [s]; lit or not), None when the file
    switches none (lite then derives them from the trajectory)."""

    name: str
    blueprint: str
    length: float
    width: float
    height: float
    wheelbase: float
    properties: dict[str, str]
    start: np.ndarray
    start_speed: float
    times: np.ndarray | None = None
    poses: np.ndarray | None = None
    brake_lights: tuple[tuple[float, bool], ...] | None = None

    @property
    def is_ego(self) -> bool:
        return self.properties.get("type") == "ego_vehicle" or self.name == EGO_NAME


@dataclass(frozen=True)
class WeatherEvent:
    """A weather event: fires once simulation time exceeds ``after_s``; its Environment (None: the event only
    carries our other knobs) and the knobs of our ``CustomCommandAction``."""

    name: str
    after_s: float
    environment: OscEnvironment | None
    other_knobs: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class ParsedScenario:
    path: Path
    minor: int
    description: str
    road_file: str
    parameters: dict[str, str]
    vehicles: tuple[ParsedVehicle, ...]
    start_environment: OscEnvironment
    weather: tuple[WeatherEvent, ...]
    stop_after_s: float | None

    def vehicle(self, name: str) -> ParsedVehicle:
        for v in self.vehicles:
            if v.name == name:
                return v
        raise KeyError(name)


def _float(el: ET.Element, attr: str, where: str) -> float:
    value = el.get(attr)
    if value is None:
        raise UserInputError(f"{where}: <{el.tag}> lacks '{attr}'")
    try:
        return float(value)
    except ValueError:
        raise UserInputError(f"{where}: <{el.tag} {attr}='{value}'> is not a number") from None


def _pose(world: ET.Element, where: str) -> list[float]:
    """x, y, z, h, p of a WorldPosition (z, h and p are optional: 0)."""
    return [_float(world, f, where) if f in ("x", "y") or world.get(f) is not None else 0.0 for f in POSE_FIELDS]


def _environment(env: ET.Element, minor: int, where: str) -> OscEnvironment:
    weather = env.find("Weather")
    road = env.find("RoadCondition")
    time_of_day = env.find("TimeOfDay")
    if weather is None or road is None:
        raise UserInputError(f"{where}: an Environment needs Weather and RoadCondition")
    sun, fog, rain = weather.find("Sun"), weather.find("Fog"), weather.find("Precipitation")
    if sun is None or fog is None or rain is None:
        raise UserInputError(f"{where}: Weather needs Sun, Fog and Precipitation to set lite's weather")
    sun_key = "intensity" if "intensity" in sun.attrib else "illuminance"  # renamed in 1.2
    rain_key = "intensity" if "intensity" in rain.attrib else "precipitationIntensity"  # renamed in 1.1
    wind = weather.find("Wind")
    hour = 12
    stamp = "" if time_of_day is None else time_of_day.get("dateTime", "")
    if "T" in stamp and stamp.split("T")[1][:2].isdigit():
        hour = int(stamp.split("T")[1][:2])
    return OscEnvironment(
        sun_intensity=_float(sun, sun_key, where) if sun_key in sun.attrib else 1.0,
        sun_azimuth=_float(sun, "azimuth", where), sun_elevation=_float(sun, "elevation", where),
        cloud_state=weather.get("cloudState", weather.get("fractionalCloudCover", "free")),
        fog_visual_range=_float(fog, "visualRange", where), precipitation_type=rain.get("precipitationType", "dry"),
        precipitation_intensity=_float(rain, rain_key, where) if rain_key in rain.attrib else 0.0,
        friction_scale_factor=_float(road, "frictionScaleFactor", where),
        wetness=road.get("wetness"), wind_speed=None if wind is None else _float(wind, "speed", where), hour=hour)


def _knobs_command(action: ET.Element, where: str) -> dict[str, float]:
    cmd = action.find("UserDefinedAction/CustomCommandAction")
    if cmd is None or cmd.get("type") != KNOBS_COMMAND:
        return {}
    try:
        values = json.loads(cmd.text or "{}")
    except json.JSONDecodeError as e:
        raise UserInputError(f"{where}: CustomCommandAction {KNOBS_COMMAND} is not JSON ({e})") from None
    return {str(k): float(v) for k, v in values.items()}


def _brake_light_switch(action: ET.Element, where: str) -> bool | None:
    """Whether an action lights (True) or puts out (False) the brake lights: a ``LightStateAction`` on
    ``brakeLights`` (1.2 on) or our command; None for any other action."""
    light = action.find("PrivateAction/AppearanceAction/LightStateAction")
    if light is not None:
        kind = light.find("LightType/VehicleLight")
        if kind is None or kind.get("vehicleLightType") != "brakeLights":
            return None
        state = light.find("LightState")
        mode = None if state is None else state.get("mode")
    else:
        cmd = action.find("UserDefinedAction/CustomCommandAction")
        if cmd is None or cmd.get("type") != BRAKE_LIGHTS_COMMAND:
            return None
        mode = (cmd.text or "").strip()
    if mode not in ("on", "off"):
        raise UserInputError(f"{where}: a brake-light action with mode '{mode}'; allowed: on, off")
    return mode == "on"


def _trigger_after(event: ET.Element, where: str) -> float | None:
    cond = event.find("StartTrigger/ConditionGroup/Condition/ByValueCondition/SimulationTimeCondition")
    return None if cond is None else _float(cond, "value", f"{where}: event '{event.get('name')}'")


def read_scenario(path: Path | str) -> ParsedScenario:
    """Parse ``path`` with scenariogeneration's reader and read what lite replays from it."""
    path = Path(path)
    if not path.is_file():
        raise UserInputError(f"scenario '{path}' does not exist")
    minor = scenario_minor_version(path)
    xosc = require_scenariogeneration().xosc
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # the reader prints the version it detected
            root = xosc.ParseOpenScenario(str(path)).get_element()
    except Exception as e:  # the reader raises its own and KeyError/AttributeError on what it cannot read
        raise UserInputError(f"scenariogeneration could not read '{path}': {type(e).__name__}: {e}") from None
    where = str(path)
    header = root.find("FileHeader")
    params = {p.get("name", ""): p.get("value", "")
              for p in root.iterfind("ParameterDeclarations/ParameterDeclaration")}
    logic = root.find("RoadNetwork/LogicFile")
    init = root.find("Storyboard/Init/Actions")
    if init is None:
        raise UserInputError(f"{where}: no Storyboard/Init")
    starts: dict[str, list[float]] = {}
    speeds: dict[str, float] = {}
    for private in init.iterfind("Private"):
        name = private.get("entityRef", "")
        world = private.find("PrivateAction/TeleportAction/Position/WorldPosition")
        if world is not None:
            starts[name] = _pose(world, where)
        speed = private.find("PrivateAction/LongitudinalAction/SpeedAction/SpeedActionTarget/AbsoluteTargetSpeed")
        if speed is not None:
            speeds[name] = _float(speed, "value", where)
    start_env = init.find("GlobalAction/EnvironmentAction/Environment")
    if start_env is None:
        raise UserInputError(f"{where}: Init has no EnvironmentAction; lite needs the start weather")

    trajectories: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    lights: dict[str, list[tuple[float, bool]]] = {}
    weather: list[WeatherEvent] = []
    for group in root.iterfind(".//ManeuverGroup"):
        actors = [a.get("entityRef", "") for a in group.iterfind("Actors/EntityRef")]
        for event in group.iterfind("Maneuver/Event"):
            for action in event.iterfind("Action"):
                polyline = action.find("PrivateAction/RoutingAction/FollowTrajectoryAction//Shape/Polyline")
                if polyline is not None and actors:
                    times: list[float] = []
                    poses: list[list[float]] = []
                    for vertex in polyline.iterfind("Vertex"):
                        world = vertex.find("Position/WorldPosition")
                        if world is None:
                            raise UserInputError(f"{where}: {actors[0]}'s trajectory has a vertex without a "
                                                 "WorldPosition (only world positions are read)")
                        times.append(_float(vertex, "time", where))
                        poses.append(_pose(world, where))
                    trajectories[actors[0]] = (np.array(times), np.array(poses))
                lit = _brake_light_switch(action, where)
                if lit is not None and actors:
                    after = _trigger_after(event, where)
                    lights.setdefault(actors[0], []).append((-1.0 if after is None else after, lit))
            name = event.get("name", "")
            if name == START_KNOBS_EVENT or name.startswith(STEP_WEATHER_EVENT):
                env_el = event.find("Action/GlobalAction/EnvironmentAction/Environment")
                other: dict[str, float] = {}
                for action in event.iterfind("Action"):
                    other.update(_knobs_command(action, where))
                after = _trigger_after(event, where)
                weather.append(WeatherEvent(name, -1.0 if after is None else after,
                                            None if env_el is None else _environment(env_el, minor, where), other))

    vehicles = []
    for obj in root.iterfind("Entities/ScenarioObject"):
        name = obj.get("name", "")
        veh = obj.find("Vehicle")
        if veh is None:
            continue
        dims = veh.find("BoundingBox/Dimensions")
        front, rear = veh.find("Axles/FrontAxle"), veh.find("Axles/RearAxle")
        if dims is None or front is None or rear is None:
            raise UserInputError(f"{where}: vehicle '{name}' needs a BoundingBox and axles")
        if name not in starts:
            raise UserInputError(f"{where}: vehicle '{name}' has no TeleportAction to a WorldPosition in Init")
        props = {p.get("name", ""): p.get("value", "") for p in veh.iterfind("Properties/Property")}
        recorded = trajectories.get(name)
        vehicles.append(ParsedVehicle(
            name=name, blueprint=veh.get("name", ""), length=_float(dims, "length", where),
            width=_float(dims, "width", where), height=_float(dims, "height", where),
            wheelbase=_float(front, "positionX", where) - _float(rear, "positionX", where), properties=props,
            start=np.array(starts[name]), start_speed=speeds.get(name, 0.0),
            times=None if recorded is None else recorded[0], poses=None if recorded is None else recorded[1],
            brake_lights=tuple(sorted(lights[name])) if name in lights else None))
    stop = root.find("Storyboard/StopTrigger/ConditionGroup/Condition/ByValueCondition/SimulationTimeCondition")
    return ParsedScenario(
        path=path, minor=minor, description="" if header is None else header.get("description", ""),
        road_file="" if logic is None else logic.get("filepath", ""), parameters=params, vehicles=tuple(vehicles),
        start_environment=_environment(start_env, minor, where),
        weather=tuple(sorted(weather, key=lambda w: w.after_s)),
        stop_after_s=None if stop is None else _float(stop, "value", f"{where}: the StopTrigger"))
