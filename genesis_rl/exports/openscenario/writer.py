"""An :class:`EpisodeTrace` as an ASAM OpenSCENARIO 1.x file, written with scenariogeneration.

What goes where (docs/openscenario.md has the full mapping):

- the road: ``RoadNetwork/LogicFile`` names the map's OpenDRIVE file written beside the scenario;
- the vehicles: one ``ScenarioObject`` each, the ego named ``hero`` with the property ``type = ego_vehicle``
  (how CARLA ScenarioRunner finds the vehicle the user's stack drives), the others ``vehicle_<id>``; the
  ``Vehicle`` name is a CARLA blueprint of the lite make, its box and axles are the make's;
- the start: ``TeleportAction`` to a ``WorldPosition`` and an ``AbsoluteSpeedAction`` per vehicle; positions
  are the standard's reference point, the rear axle's centre on the road (lite's poses are box centres);
- the motion: every other vehicle follows its recorded path (``FollowTrajectoryAction``, a time-stamped
  ``Polyline`` with a vertex per step, absolute time); the ego's own path is there too as the reference, in
  an event that starts only when the parameter ``GenesisEgoFollowsReference`` is set true, so by default the
  user's stack drives;
- the brake lights of every other vehicle, switched where lite switched them: ``LightStateAction`` from 1.3 on,
  our ``CustomCommandAction`` of type ``genesis-rl:brake-lights`` before;
- the weather: an ``EnvironmentAction`` at the start and at every step whose knobs changed
  (``environment.environment_of``), and beside it a ``CustomCommandAction`` of type ``genesis-rl:knobs``
  with the knobs the standard cannot carry (other tools ignore it);
- lite's own start state (lane, arc length, next lane per vehicle; the signal clock; the episode seed;
  the system that failed) as ``Properties`` and ``ParameterDeclarations`` named ``genesis.*`` / ``Genesis*``;
- the end: the storyboard stops at the episode's last step.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl import __version__
from genesis_rl.core.files.io_utils import atomic_write_text
from genesis_rl.exports.openscenario.environment import DATE, OscEnvironment, environment_of, expressed_knobs
from genesis_rl.exports.openscenario.trace import EpisodeTrace, VehicleTrack
from genesis_rl.sim.lite.maps.opendrive import wrap_angle
from genesis_rl.sim.lite.traffic import MAX_BRAKE, MAX_STEER
from genesis_rl.world.scenes.vehicles import MAKES

EGO_NAME = "hero"
KNOBS_COMMAND = "genesis-rl:knobs"
EGO_REFERENCE_PARAMETER = "GenesisEgoFollowsReference"
START_KNOBS_EVENT = "weather_start_knobs"
STEP_WEATHER_EVENT = "weather_step_"  # + the step whose knobs it sets
#: the first minor version whose ``LightStateAction`` we write: 1.2 has the action, but its XSD's ``LightType``
#: demands a ``VehicleLight`` and a ``UserDefinedLight`` together (a sequence; 1.3 made it a choice)
LIGHT_STATE_MINOR = 3
#: our command for a vehicle's brake lights before :data:`LIGHT_STATE_MINOR` (``on`` / ``off``)
BRAKE_LIGHTS_COMMAND = "genesis-rl:brake-lights"
BRAKE_LIGHTS_EVENT = "_brake_lights_"  # vehicle name + this + the sample (step) from which the lights hold
#: CARLA 0.9.16 blueprint and OpenSCENARIO category written for each lite make
BLUEPRINT = {"sedan": "vehicle.tesla.model3", "hatchback": "vehicle.mini.cooper_s_2021", "suv": "vehicle.audi.etron",
             "van": "vehicle.volkswagen.t2_2021", "truck": "vehicle.carlamotors.european_hgv",
             "bus": "vehicle.mitsubishi.fusorosa"}
CATEGORY = {"sedan": "car", "hatchback": "car", "suv": "car", "van": "van", "truck": "truck", "bus": "bus"}
WHEEL_DIAMETER = 0.7  # [m]


def vehicle_name(vehicle_id: int) -> str:
    return EGO_NAME if vehicle_id == 0 else f"vehicle_{vehicle_id}"


def rear_axle(track: VehicleTrack) -> tuple[np.ndarray, np.ndarray]:
    """The rear axle's centre (the standard's vehicle reference point) of a track's box centres."""
    half = 0.5 * MAKES[track.make].wheelbase
    return track.x - half * np.cos(track.yaw), track.y - half * np.sin(track.yaw)


def _position(xosc: Any, x: float, y: float, z: float, yaw: float, pitch: float) -> Any:
    # OpenSCENARIO's pitch turns about the vehicle's y axis (to its left), so a positive pitch lowers the nose;
    # lite's pitch is nose-up positive. Every number at full precision (Python's shortest repr, read back to the
    # bit): a pose rounded to 0.1 mm moves the pixels the system under test sees, and a marginal failure then
    # does not replay from the file
    return xosc.WorldPosition(x=float(x), y=float(y), z=float(z), h=wrap_angle(float(yaw)), p=-float(pitch), r=0.0)


def _vehicle(xosc: Any, track: VehicleTrack) -> Any:
    make = MAKES[track.make]
    track_width = round(0.85 * make.width, 3)
    v = xosc.Vehicle(
        BLUEPRINT[track.make], getattr(xosc.VehicleCategory, CATEGORY[track.make]),
        xosc.BoundingBox(make.width, make.length, make.height, 0.5 * make.wheelbase, 0.0, 0.5 * make.height),
        xosc.Axle(float(MAX_STEER), WHEEL_DIAMETER, track_width, make.wheelbase, 0.5 * WHEEL_DIAMETER),
        xosc.Axle(0.0, WHEEL_DIAMETER, track_width, 0.0, 0.5 * WHEEL_DIAMETER),
        make.max_speed, make.max_accel, MAX_BRAKE)
    if track.vehicle_id == 0:
        v.add_property("type", "ego_vehicle")
    for key, value in (("genesis.make", track.make), ("genesis.color", track.color_name),
                       ("genesis.vehicle_id", track.vehicle_id), ("genesis.lane", track.lane),
                       ("genesis.s", repr(float(track.s))), ("genesis.next_lane", track.next_lane)):
        v.add_property(key, str(value))
    return v


def _g(v: float) -> float:
    """``v`` at full precision. Rounded to 10 significant digits (until 0.30.0, to spare the file float noise
    such as 2999.9999999999977), the sun's angles came back 3e-8 degrees off the recorded knobs."""
    return float(v)


def _environment(xosc: Any, env: OscEnvironment, minor: int) -> Any:
    cloud = (getattr(xosc.FractionalCloudCover, env.cloud_state) if minor >= 2
             else getattr(xosc.CloudState, env.cloud_state))
    weather = xosc.Weather(
        cloudstate=cloud,
        sun=xosc.Sun(_g(env.sun_intensity), _g(env.sun_azimuth), _g(env.sun_elevation)),
        fog=xosc.Fog(_g(env.fog_visual_range)),
        precipitation=xosc.Precipitation(getattr(xosc.PrecipitationType, env.precipitation_type),
                                         _g(env.precipitation_intensity)),
        wind=None if env.wind_speed is None else xosc.Wind(0.0, _g(env.wind_speed)))
    road = xosc.RoadCondition(_g(env.friction_scale_factor),
                              wetness=None if env.wetness is None else getattr(xosc.Wetness, env.wetness))
    year, month, day = DATE
    return xosc.Environment("genesis_weather", xosc.TimeOfDay(False, year, month, day, env.hour, 0, 0), weather, road)


def _weather_actions(xosc: Any, knobs: dict[str, float], minor: int) -> tuple[Any, Any]:
    """The EnvironmentAction and our CustomCommandAction (the knobs the standard cannot carry) of a step."""
    env = xosc.EnvironmentAction(_environment(xosc, environment_of(knobs, minor), minor))
    rest = {k: v for k, v in knobs.items() if k not in expressed_knobs(minor)}
    return env, xosc.CustomCommandAction(KNOBS_COMMAND, json.dumps(rest, sort_keys=True))


def _time_trigger(xosc: Any, name: str, after_s: float) -> Any:
    return xosc.ValueTrigger(name, 0, xosc.ConditionEdge.none,
                             xosc.SimulationTimeCondition(round(after_s, 6), xosc.Rule.greaterThan))


def polyline_vertices(times: np.ndarray, path: np.ndarray, tolerance: np.ndarray) -> list[int]:
    """The samples to keep of a time-stamped path (rows of times, columns x, y, z, yaw, ...): few, chosen
    greedily (each segment grows until one more sample would put a dropped one outside ``tolerance``, per
    column, of the linear interpolation in time). The first and last are always kept."""
    keep = [0]
    start = 0
    n = len(times)
    while start < n - 1:
        end = start + 1
        while end + 1 < n:
            cand = end + 1
            u = (times[start + 1:cand] - times[start]) / (times[cand] - times[start])
            between = path[start] + u[:, None] * (path[cand] - path[start])
            if np.any(np.abs(between - path[start + 1:cand]) > tolerance):
                break
            end = cand
        keep.append(end)
        start = end
    return keep


#: how far a dropped vertex may lie from the polyline through the kept ones: nothing, so the file is lossless
#: (a vertex is dropped only where the line through its neighbours gives it exactly, as while a vehicle stands);
#: 2 mm and 0.5 mrad, as until 0.30.0, made marginal failures replay differently from the file
VERTEX_TOLERANCE = np.zeros(5)


def _follow(xosc: Any, trace: EpisodeTrace, track: VehicleTrack) -> Any:
    xr, yr = rear_axle(track)
    path = np.column_stack([xr, yr, track.z, track.yaw, track.pitch])
    keep = polyline_vertices(trace.times, path, VERTEX_TOLERANCE)
    positions = [_position(xosc, xr[k], yr[k], track.z[k], track.yaw[k], track.pitch[k]) for k in keep]
    trajectory = xosc.Trajectory(f"{vehicle_name(track.vehicle_id)}_recorded", False)
    trajectory.add_shape(xosc.Polyline([round(float(trace.times[k]), 6) for k in keep], positions))
    return xosc.FollowTrajectoryAction(trajectory, xosc.FollowingMode.position, xosc.ReferenceContext.absolute, 1, 0)


def brake_light_changes(braking: np.ndarray) -> list[tuple[int, bool]]:
    """(sample, lit) wherever a vehicle's brake lights change, starting from unlit (as lite starts them)."""
    lit = np.asarray(braking, bool)
    before = np.concatenate([[False], lit[:-1]])
    return [(int(k), bool(lit[k])) for k in np.flatnonzero(lit != before)]


def _brake_lights(xosc: Any, trace: EpisodeTrace, track: VehicleTrack, minor: int) -> Any | None:
    """A maneuver that switches a vehicle's brake lights where lite switched them: lite lights them from the
    commanded deceleration, which the trajectory shows only smoothed, and the system under test sees them.
    ``LightStateAction`` from 1.3 on, our ``CustomCommandAction`` before; each fired half a step before its
    sample, as the weather's are. Parallel priority: a light event must not stop the vehicle's trajectory."""
    if track.braking is None or track.vehicle_id == 0:  # the ego's lights follow its own driver's brake
        return None
    changes = brake_light_changes(track.braking)
    if not changes:
        return None
    name = vehicle_name(track.vehicle_id)
    maneuver = xosc.Maneuver(f"{name}_brake_lights")
    for k, lit in changes:
        mode = "on" if lit else "off"
        if minor >= LIGHT_STATE_MINOR:
            action = xosc.LightStateAction(xosc.VehicleLightType.brakeLights, getattr(xosc.LightMode, mode))
        else:
            action = xosc.UserDefinedAction(xosc.CustomCommandAction(BRAKE_LIGHTS_COMMAND, mode))
        event = xosc.Event(f"{name}{BRAKE_LIGHTS_EVENT}{k}", xosc.Priority.parallel)
        event.add_action(f"{name}_brake_lights_{mode}_{k}", action)
        event.add_trigger(_time_trigger(xosc, f"{name}_brake_lights_{k}_time", (k - 0.5) * trace.dt))
        maneuver.add_event(event)
    return maneuver


def describe(trace: EpisodeTrace) -> str:
    what = "no collision"
    if trace.first_collision_step is not None:
        what = (f"the ego hit {vehicle_name(int(trace.collision_with or 0))} at step {trace.first_collision_step} "
                f"(t = {trace.first_collision_step * trace.dt:.2f} s)")
    return (f"GENESIS-RL {__version__} edge case {trace.name}: policy {trace.policy or '-'}, scene "
            f"{trace.scene_index} of map {trace.map}; {what}")


def build_scenario(trace: EpisodeTrace, xodr_file: str, minor: int = 0) -> Any:
    """The scenariogeneration ``Scenario`` of a trace (``xodr_file``: the map's path as the file names it)."""
    from scenariogeneration import xosc
    from scenariogeneration.xosc.enumerations import VersionBase

    VersionBase().setVersion(minor=minor)  # scenariogeneration checks enumerations against a global version
    priority = xosc.Priority.overwrite if minor < 2 else xosc.Priority.override  # renamed in 1.2
    integer = xosc.ParameterType.integer if minor < 2 else xosc.ParameterType.int  # renamed in 1.2
    params = xosc.ParameterDeclarations()
    for name, kind, value in (
            (EGO_REFERENCE_PARAMETER, xosc.ParameterType.boolean, "false"),
            ("GenesisMap", xosc.ParameterType.string, trace.map),
            ("GenesisEpisodeSeed", integer, str(trace.episode_seed)),
            ("GenesisSceneSeed", integer, str(trace.scene_seed)),
            ("GenesisWorldSeed", integer, str(trace.episode_seed if trace.world_seed is None else trace.world_seed)),
            ("GenesisSignalOffset", xosc.ParameterType.double, repr(float(trace.signal_offset))),
            ("GenesisStepSeconds", xosc.ParameterType.double, repr(float(trace.dt))),
            ("GenesisCamera", xosc.ParameterType.string, f"{trace.camera[0]}x{trace.camera[1]}"),
            ("GenesisSystem", xosc.ParameterType.string, json.dumps(trace.system, sort_keys=True)),
            ("GenesisRulebook", xosc.ParameterType.string, json.dumps(trace.rulebook, sort_keys=True))):
        params.add_parameter(xosc.Parameter(name, kind, value))

    entities = xosc.Entities()
    init = xosc.Init()
    for track in trace.vehicles:
        name = vehicle_name(track.vehicle_id)
        entities.add_scenario_object(name, _vehicle(xosc, track))
        xr, yr = rear_axle(track)
        init.add_init_action(name, xosc.TeleportAction(
            _position(xosc, xr[0], yr[0], track.z[0], track.yaw[0], track.pitch[0])))
        init.add_init_action(name, xosc.AbsoluteSpeedAction(
            float(track.speed[0]), xosc.TransitionDynamics(xosc.DynamicsShapes.step,
                                                                     xosc.DynamicsDimension.time, 0)))
    env, custom = _weather_actions(xosc, trace.start_weather, minor)
    init.add_global_action(env)

    act = xosc.Act("episode", _time_trigger(xosc, "episode_start", -1.0))
    weather = xosc.Maneuver("weather_schedule")
    # the start's other knobs: an event, not Init, whose user-defined actions scenariogeneration 0.16.7 writes
    # without their UserDefinedAction element (invalid) and cannot read back
    event = xosc.Event(START_KNOBS_EVENT, priority)
    event.add_action("knobs_start", xosc.UserDefinedAction(custom))
    event.add_trigger(_time_trigger(xosc, "weather_start_time", -1.0))
    weather.add_event(event)
    for track in trace.vehicles:
        name = vehicle_name(track.vehicle_id)
        event = xosc.Event(f"{name}_follows_recording", priority)
        event.add_action(f"{name}_trajectory", _follow(xosc, trace, track))
        if track.vehicle_id == 0:  # the reference path: only when the user asks the ego to replay it
            event.add_trigger(xosc.ValueTrigger("ego_reference_requested", 0, xosc.ConditionEdge.none,
                                                xosc.ParameterCondition(EGO_REFERENCE_PARAMETER, "true",
                                                                        xosc.Rule.equalTo)))
        else:
            event.add_trigger(_time_trigger(xosc, f"{name}_start", -1.0))
        maneuver = xosc.Maneuver(f"{name}_recorded_motion")
        maneuver.add_event(event)
        group = xosc.ManeuverGroup(f"{name}_group")
        group.add_actor(name)
        group.add_maneuver(maneuver)
        lights = _brake_lights(xosc, trace, track, minor)
        if lights is not None:
            group.add_maneuver(lights)
        act.add_maneuver_group(group)

    previous = None
    for k, row in enumerate(trace.schedule):
        if previous is not None and np.array_equal(row, previous):
            continue
        previous = row
        knobs = dict(zip(trace.knob_names, map(float, row), strict=True))
        env, custom = _weather_actions(xosc, knobs, minor)
        event = xosc.Event(f"{STEP_WEATHER_EVENT}{k}", priority)
        event.add_action(f"weather_{k}", env)
        event.add_action(f"knobs_{k}", xosc.UserDefinedAction(custom))
        event.add_trigger(_time_trigger(xosc, f"weather_{k}_time", (k - 0.5) * trace.dt))
        weather.add_event(event)
    group = xosc.ManeuverGroup("weather_group")
    group.add_maneuver(weather)
    act.add_maneuver_group(group)

    story = xosc.Story("genesis_episode")
    story.add_act(act)
    end = xosc.ConditionGroup()
    end.add_condition(_time_trigger(xosc, "episode_end", trace.duration))
    stop = xosc.Trigger("stop")
    stop.add_conditiongroup(end)
    board = xosc.StoryBoard(init, stop)
    board.add_story(story)
    return xosc.Scenario(describe(trace), "genesis-rl", params, entities, board, xosc.RoadNetwork(xodr_file),
                         xosc.Catalog(), osc_minor_version=minor)


def write_scenario(trace: EpisodeTrace, path: Path, xodr_file: str, minor: int = 0) -> None:
    """Write the trace's scenario to ``path`` (atomically: a temporary file, then renamed)."""
    scenario = build_scenario(trace, xodr_file, minor)
    root = scenario.get_element()
    for light in root.iter("LightStateAction"):  # scenariogeneration 0.16.7 writes LightState first; the XSD
        kind = light.find("LightType")            # wants LightType first (the file is otherwise invalid)
        if kind is not None:
            light.remove(kind)
            light.insert(0, kind)
    ET.indent(root, space=" ")  # scenariogeneration's pretty print indents by 4 per level: 4x the size
    text = ET.tostring(root, encoding="unicode", xml_declaration=False)
    atomic_write_text(path, '<?xml version="1.0" encoding="utf-8"?>\n' + text + "\n")
