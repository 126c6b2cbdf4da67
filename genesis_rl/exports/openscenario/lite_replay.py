"""Drive lite from a parsed OpenSCENARIO file: the file's vehicles on their trajectories, the weather from its
Environment actions, a system under test driving the ego.

- the scene: each vehicle where its ``TeleportAction`` puts it (the rear axle's centre, so the box centre is
  half a wheelbase ahead), at its ``AbsoluteSpeedAction`` speed; lite's lane, arc length and next lane come
  from the ``genesis.*`` properties when they agree with the position (within :data:`MAX_PROPERTY_OFFSET`),
  else from the lane nearest the position;
- the motion: a vehicle with a trajectory is scripted (``traffic.ScriptedMotion``): its pose after every step
  is the polyline's, linearly interpolated in time, height and pitch included; its speed is the distance it
  covers around the step over the time; its brake lights switch where the file switches them
  (``LightStateAction`` or our command), else they are lit while it slows by more than 0.5 m/s^2 or stands; a
  vehicle without a trajectory drives on lite's autopilot;
- the weather: at the start, the Init's Environment; before step k + 1 (time k dt), the last weather event
  that has fired by then. The knobs the standard carries come from the Environment
  (``environment.knobs_from_environment``), the others from our ``CustomCommandAction`` (default when the
  file has none); actor knobs stay at their defaults (the trajectories already hold what the actors did).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.exports.openscenario.environment import expressed_knobs, knobs_from_environment
from genesis_rl.exports.openscenario.reader import ParsedScenario, ParsedVehicle, WeatherEvent
from genesis_rl.exports.openscenario.trace import first_collision
from genesis_rl.exports.openscenario.writer import BLUEPRINT, KNOBS_COMMAND, START_KNOBS_EVENT
from genesis_rl.sim.interface import FIXED_DELTA_SECONDS, Simulation
from genesis_rl.sim.lite.maps import MAP_NAMES, load_map
from genesis_rl.sim.lite.maps.lane_graph import DS, RoadMap
from genesis_rl.sim.lite.traffic import BRAKE_LIGHT_DECEL, ScriptedMotion
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.scenes.catalog import Scene, VehicleSpec
from genesis_rl.world.scenes.vehicles import MAKES, PALETTE
from genesis_rl.world.step_record import StepRecord

MAX_PROPERTY_OFFSET = 1.0  # [m] how far the genesis.lane/s start may lie from the file's position
STANDING = 0.05  # [m/s]
MAX_OFF_LANE = 5.0  # [m] a start farther than this from every lane is not on this map


@dataclass(frozen=True)
class ScenarioDrive:
    """What lite did with a scenario: step records, the ego's first collision, the violations of the rulebook,
    and where each knob came from (``standard``: the Environment; ``genesis``: our custom action; ``default``)."""

    records: list[StepRecord]
    first_collision_step: int | None
    collision_with: int | None
    violations: dict[str, float]
    knob_sources: dict[str, str]
    scripted: int
    weathers: list[Weather]


def _map_name(parsed: ParsedScenario) -> str:
    name = parsed.parameters.get("GenesisMap") or parsed.road_file.rsplit("/", 1)[-1].removesuffix(".xodr")
    if name not in MAP_NAMES:
        raise UserInputError(f"{parsed.path}: road network '{parsed.road_file}' is not a lite map; lite replays "
                             f"scenarios on {', '.join(MAP_NAMES)} (GenesisMap or LogicFile MAP.xodr)")
    return name


def _make(v: ParsedVehicle) -> str:
    make = v.properties.get("genesis.make")
    if make in MAKES:
        return str(make)
    by_blueprint = {bp: m for m, bp in BLUEPRINT.items()}
    if v.blueprint in by_blueprint:
        return by_blueprint[v.blueprint]
    return min(MAKES, key=lambda m: abs(MAKES[m].length - v.length))  # the make of the nearest length


def _centre(v: ParsedVehicle, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box centres (lite's poses) of rear-axle poses (the file's reference points): half a wheelbase ahead."""
    pose = np.atleast_2d(pose)
    half = 0.5 * v.wheelbase
    return pose[:, 0] + half * np.cos(pose[:, 3]), pose[:, 1] + half * np.sin(pose[:, 3]), pose[:, 3]


def _lane_start(road_map: RoadMap, v: ParsedVehicle, x: float, y: float, yaw: float) -> tuple[int, float, int]:
    """(lane, arc length, next lane) of a vehicle at (x, y): the genesis.* properties when they agree with the
    position, else the nearest lane sample in the vehicle's heading and its first successor."""
    p = v.properties
    try:
        lane, s, nxt = int(p["genesis.lane"]), float(p["genesis.s"]), int(p["genesis.next_lane"])
        idx = int(road_map.point_index(np.array([lane]), np.array([s]))[0])
        if math.hypot(road_map.points[idx, 0] - x, road_map.points[idx, 1] - y) <= MAX_PROPERTY_OFFSET + DS:
            return lane, s, nxt
    except (KeyError, ValueError, IndexError):
        pass
    k = road_map.nearest_lane_point(x, y, yaw)
    if math.hypot(road_map.points[k, 0] - x, road_map.points[k, 1] - y) > MAX_OFF_LANE:
        raise UserInputError(f"vehicle '{v.name}' starts at ({x:.1f}, {y:.1f}), over {MAX_OFF_LANE:g} m from every "
                             f"lane of lite's map '{road_map.name}'")
    lane = int(road_map.point_lane[k])
    s = (k - int(road_map.offset[lane])) * DS
    h = road_map.headings[k]
    s += (x - road_map.points[k, 0]) * math.cos(h) + (y - road_map.points[k, 1]) * math.sin(h)
    return lane, max(s, 0.0), road_map.lanes[lane].successors[0]


def _script(v: ParsedVehicle, dt: float, steps: int) -> ScriptedMotion:
    """The vehicle's pose after every step (row k: time (k + 1) dt) from its polyline."""
    assert v.times is not None and v.poses is not None
    # the start and after every step, to the microsecond the writer rounds vertex times to, so a sample falls on
    # its vertex exactly and the pose is the file's to the bit
    t = np.round(np.arange(steps + 1) * dt, 6)
    yaw_path = np.unwrap(v.poses[:, 3])
    pose = np.column_stack([np.interp(t, v.times, v.poses[:, 0]), np.interp(t, v.times, v.poses[:, 1]),
                            np.interp(t, v.times, v.poses[:, 2]), np.interp(t, v.times, yaw_path)])
    pitch = -np.interp(t, v.times, v.poses[:, 4])  # the file's pitch is nose down, lite's nose up
    x, y, yaw = _centre(v, pose)
    chord = np.hypot(np.diff(x), np.diff(y)) / dt  # mean speed over each step
    speed = np.empty(steps + 1)
    speed[0], speed[-1] = chord[0], chord[-1]  # the ends: the one step beside them
    speed[1:-1] = 0.5 * (chord[:-1] + chord[1:])  # inside: the mean of the steps before and after the sample
    speed = np.where(speed < 1e-6, 0.0, speed)
    if v.brake_lights is not None:  # the file switches them: as lite lit them when the episode ran
        braking = np.zeros(steps + 1, bool)
        for after, lit in v.brake_lights:  # in time order: a later switch overrides
            braking[t > after + 1e-9] = lit
    else:  # a file that does not: lit while the trajectory slows faster than lite's threshold, or stands
        slowing = np.diff(speed, prepend=speed[0]) / dt < -BRAKE_LIGHT_DECEL
        braking = slowing | (speed < STANDING)
    return ScriptedMotion(x=x[1:], y=y[1:], yaw=yaw[1:], speed=speed[1:], braking=braking[1:], z=pose[1:, 2],
                          pitch=pitch[1:])


def _knobs(event_env: Any, other: dict[str, float], minor: int, base: Weather) -> tuple[Weather, dict[str, str]]:
    """``base`` with what an event sets: its Environment's knobs, then the other knobs of our command (actor
    knobs excepted). What the event does not carry stays as it was."""
    values = base.as_dict()
    sources: dict[str, str] = {}
    for name, value in other.items():
        if name not in KNOBS:
            raise UserInputError(f"CustomCommandAction {KNOBS_COMMAND}: unknown knob '{name}'; allowed: "
                                 f"{', '.join(KNOBS)}")
        if not KNOBS[name].is_actor:
            values[name] = value
            sources[name] = "genesis"
    if event_env is not None:
        for name, value in knobs_from_environment(event_env, minor).items():
            values[name] = value
            sources[name] = "standard"
    return Weather.from_partial(values), sources


def scenario_weathers(parsed: ParsedScenario, dt: float, steps: int) -> tuple[Weather, list[Weather], dict[str, str]]:
    """The start weather and the weather set before every step (an event's weather holds from the step at whose
    time it has fired), and each knob's source (``standard``, ``genesis`` or ``default``)."""
    start_other = next((w.other_knobs for w in parsed.weather if w.name == START_KNOBS_EVENT), {})
    start, sources = _knobs(parsed.start_environment, start_other, parsed.minor, Weather.default())
    sources = {**dict.fromkeys(KNOBS, "default"), **sources}
    events: list[WeatherEvent] = [w for w in parsed.weather if w.name != START_KNOBS_EVENT]
    out = []
    current, j = start, 0
    for k in range(steps):
        while j < len(events) and events[j].after_s < k * dt - 1e-9:
            current, s = _knobs(events[j].environment, events[j].other_knobs, parsed.minor, current)
            sources.update(s)
            j += 1
        out.append(current)
    return start, out, sources


def _parameter(parsed: ParsedScenario, name: str, default: str, kind: type, allowed: str) -> Any:
    value = parsed.parameters.get(name, default)
    try:
        return kind(value)
    except ValueError:
        raise UserInputError(f"{parsed.path}: parameter {name} = '{value}'; allowed: {allowed}") from None


def _camera(parsed: ParsedScenario) -> tuple[int, int]:
    value = parsed.parameters.get("GenesisCamera", "320x240")
    parts = value.split("x")
    if len(parts) != 2 or not all(p.isdigit() and 16 <= int(p) <= 4096 for p in parts):
        raise UserInputError(f"{parsed.path}: parameter GenesisCamera = '{value}'; allowed: WIDTHxHEIGHT, each "
                             "16..4096")
    return int(parts[0]), int(parts[1])


def scene_of(parsed: ParsedScenario) -> tuple[Scene, dict[int, ScriptedMotion], float, int]:
    """The lite scene, the scripts of the vehicles with trajectories, the step length and the step count."""
    map_name = _map_name(parsed)
    road_map = load_map(map_name)
    dt = _parameter(parsed, "GenesisStepSeconds", str(FIXED_DELTA_SECONDS), float, f"{FIXED_DELTA_SECONDS}")
    if abs(dt - FIXED_DELTA_SECONDS) > 1e-9:
        raise UserInputError(f"{parsed.path}: parameter GenesisStepSeconds = {dt}; allowed: {FIXED_DELTA_SECONDS} "
                             "(lite's step)")
    if parsed.stop_after_s is None:
        raise UserInputError(f"{parsed.path}: the storyboard has no SimulationTime stop trigger; lite needs the "
                             "episode's length")
    steps = int(round(parsed.stop_after_s / dt))
    ordered = sorted(parsed.vehicles, key=lambda v: (not v.is_ego, int(v.properties.get("genesis.vehicle_id", 10**6))))
    if not ordered or not ordered[0].is_ego:
        raise UserInputError(f"{parsed.path}: no ego vehicle (a ScenarioObject 'hero' or property type=ego_vehicle)")
    specs, scripts = [], {}
    for i, v in enumerate(ordered):
        x, y, yaw = (float(a[0]) for a in _centre(v, v.start))
        lane, s, nxt = _lane_start(road_map, v, x, y, yaw)
        make = _make(v)
        color = v.properties.get("genesis.color", "white")
        autopilot = None if i == 0 else {"target_speed": max(v.start_speed, 1.0), "time_gap": 1.5, "min_gap": 2.0,
                                         "max_accel": 2.0, "comfort_decel": 3.0, "stop_rate": 0.0,
                                         "speed_noise": 0.0}
        specs.append(VehicleSpec("ego" if i == 0 else "npc", make, color, PALETTE.get(color, PALETTE["white"]), lane,
                                 s, x, y, yaw, v.start_speed, nxt, autopilot))
        if i > 0 and v.times is not None:
            scripts[i] = _script(v, dt, steps)
    scene = Scene(index=0, map=map_name, seed=_parameter(parsed, "GenesisSceneSeed", "0", int, "an integer >= 0"),
                  signal_offset=_parameter(parsed, "GenesisSignalOffset", "0", float, "a number of seconds"),
                  vehicles=tuple(specs))
    return scene, scripts, dt, steps


def drive_scenario(parsed: ParsedScenario, system_spec: str | None = None, weights: str | None = None,
                   observer: Callable[[Simulation], None] | None = None) -> ScenarioDrive:
    """Drive the scenario on lite with the file's system (``GenesisSystem``) or ``system_spec``. ``observer``
    sees the simulation after the start and after every step, as ``replay_record``'s does, so the two drives
    can be compared state by state."""
    import torch  # local: start-up cost

    from genesis_rl.campaigns.records import load_recorded_system
    from genesis_rl.loop.drive import ClosedLoop
    from genesis_rl.loop.rules.rulebook import build_rulebook, default_rulebook
    from genesis_rl.sim.interface import CameraConfig
    from genesis_rl.sim.lite.backend import LiteBackend

    torch.set_num_threads(1)  # as campaigns and replay: the same arithmetic
    scene, scripts, dt, steps = scene_of(parsed)
    start, weathers, sources = scenario_weathers(parsed, dt, steps)
    rules = parsed.parameters.get("GenesisRulebook")
    rulebook = build_rulebook(json.loads(rules), "scenario rulebook") if rules else default_rulebook()
    recorded = json.loads(parsed.parameters.get("GenesisSystem", '{"spec": "builtin"}'))
    if system_spec is not None:
        recorded = {"spec": system_spec}
    system = load_recorded_system(recorded, weights)
    width, height = _camera(parsed)
    # the world the episode ran in: a benchmark's re-run plays its episode's schedule in another world
    seed = _parameter(parsed, "GenesisWorldSeed", parsed.parameters.get("GenesisEpisodeSeed", "0"), int,
                      "an integer >= 0")
    backend = LiteBackend()
    records: list[StepRecord] = []
    try:
        lite_sim = backend.create_simulation(scene, seed=seed, weather=start,
                                             camera=CameraConfig(width=width, height=height))
        lite_sim.traffic.scripted = scripts
        with lite_sim as sim:
            loop = ClosedLoop(sim, system, backend.name, seed)
            loop.start(start)
            if observer is not None:
                observer(sim)
            for weather in weathers:
                r = loop.advance(weather)
                records.append(r.scored(rulebook.step_terms(r)))
                if observer is not None:
                    observer(sim)
    finally:
        backend.close()
    step, other = first_collision(records)
    used = {n: s for n, s in sources.items() if not KNOBS[n].is_actor}
    return ScenarioDrive(records, step, other, rulebook.violations(records), used, len(scripts), weathers)


def standard_share(drive: ScenarioDrive, minor: int) -> tuple[int, int]:
    """(knobs set from the standard's Environment, knobs the Environment can carry in this version)."""
    return sum(1 for s in drive.knob_sources.values() if s == "standard"), len(expressed_knobs(minor))

