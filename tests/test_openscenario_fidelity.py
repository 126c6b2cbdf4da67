"""An exported failure replays from its file as lite drove it: the brake lights as lite lit them, every pose to
the bit, and the struck vehicle where the ego met it (docs/openscenario.md, section 3)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("scenariogeneration")

from genesis_rl.exports.openscenario.lite_replay import _script  # noqa: E402
from genesis_rl.exports.openscenario.reader import read_scenario  # noqa: E402
from genesis_rl.exports.openscenario.schema import validate_scenario  # noqa: E402
from genesis_rl.exports.openscenario.trace import EpisodeTrace, VehicleTrack  # noqa: E402
from genesis_rl.exports.openscenario.writer import write_scenario  # noqa: E402
from genesis_rl.world.knobs import KNOBS, Weather  # noqa: E402

DT = 0.05
STEPS = 60


def _track(i: int, speed: np.ndarray, x0: float, braking: np.ndarray | None) -> VehicleTrack:
    x = x0 + np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * DT)])
    n = len(speed)
    # a slope and a height that no lane of the map has at these points, with digits past 0.1 mm
    z = 1.0 + 0.0123456789 * np.arange(n)
    return VehicleTrack(i, "ego" if i == 0 else "npc", "sedan", "white", 4.6, 1.85, 1.45, 0, float(x0), 0,
                        x + 1e-7 * np.sin(np.arange(n)), np.full(n, -1.75), z, np.zeros(n), np.full(n, 0.0123),
                        speed, braking)


def _trace() -> EpisodeTrace:
    t = np.arange(STEPS + 1) * DT
    # the lead brakes from 1 s at a deceleration that ramps up 0.2 m/s^2 a step, as the tester's lead_decel does;
    # lite lit its lights from the command (above 0.5 m/s^2 from the third step of braking)
    decel = np.clip(0.2 * (np.arange(STEPS + 1) - 20), 0.0, 6.0)
    lead = np.maximum(15.0 - np.concatenate([[0.0], np.cumsum(decel[1:] * DT)]), 0.0)
    lead_lit = decel > 0.5
    # a neighbour at a steady speed whose autopilot flickered its lights (IDM braking around 0.5 m/s^2): its
    # trajectory shows no slowing at all
    steady_lit = np.zeros(STEPS + 1, bool)
    steady_lit[[5, 6, 7, 30, 41, 42]] = True
    names = tuple(KNOBS)
    row = [Weather.default()[n] for n in names]
    return EpisodeTrace(
        name="lights", map="highway", dt=DT, times=t,
        vehicles=(_track(0, np.full(STEPS + 1, 15.0), 0.0, np.zeros(STEPS + 1, bool)),
                  _track(1, lead, 30.0, lead_lit), _track(2, np.full(STEPS + 1, 12.0), 60.0, steady_lit)),
        knob_names=names, schedule=np.array([row] * STEPS), start_weather=Weather.default().as_dict(),
        signal_offset=0.0, scene_seed=1, episode_seed=2, system={"spec": "builtin", "kwargs": {}},
        rulebook=[{"name": "collision"}], camera=(320, 240), policy="constant", scene_index=3, violations={},
        first_collision_step=None, collision_with=None)


@pytest.mark.parametrize("minor", [0, 2, 3])
def test_brake_lights_replay_as_lite_lit_them(tmp_path, minor: int) -> None:
    """Before, the replay derived the lights from the trajectory: the lead's came on a step off, and the steady
    neighbour's never (lite's detector sees brake lights)."""
    trace = _trace()
    path = tmp_path / f"lights_1_{minor}.xosc"
    write_scenario(trace, path, "highway.xodr", minor)
    assert validate_scenario(path).valid, validate_scenario(path).errors[:3]
    text = path.read_text()
    assert ("LightStateAction" in text) == (minor >= 3)  # the standard's action from 1.3 on, our command before
    assert ('type="genesis-rl:brake-lights"' in text) == (minor < 3)
    parsed = read_scenario(path)
    for track in trace.vehicles[1:]:
        script = _script(parsed.vehicle(f"vehicle_{track.vehicle_id}"), DT, STEPS)
        assert np.array_equal(script.braking, track.braking[1:]), track.vehicle_id
    assert parsed.vehicle("hero").brake_lights is None  # the ego's lights follow its own driver


def test_a_file_without_lights_still_derives_them(tmp_path) -> None:
    trace = _trace()
    bare = replace(trace, vehicles=tuple(replace(v, braking=None) for v in trace.vehicles))
    write_scenario(bare, tmp_path / "bare.xosc", "highway.xodr", 0)
    parsed = read_scenario(tmp_path / "bare.xosc")
    lead = parsed.vehicle("vehicle_1")
    assert lead.brake_lights is None
    lit = _script(lead, DT, STEPS).braking
    assert not lit[:15].any() and lit[30:].all()


def test_poses_heights_and_speeds_come_back_to_the_bit(tmp_path) -> None:
    """Before, positions were rounded to 0.1 mm and thinned at 2 mm, the start speed to 1e-6 m/s, and a script's
    height and pitch came from lite's lane: enough to flip a detection in a marginal failure."""
    trace = _trace()
    path = tmp_path / "exact.xosc"
    write_scenario(trace, path, "highway.xodr", 0)
    parsed = read_scenario(path)
    for track in trace.vehicles[1:]:
        v = parsed.vehicle(f"vehicle_{track.vehicle_id}")
        assert v.start_speed == track.speed[0]
        script = _script(v, DT, STEPS)
        assert np.max(np.abs(script.x - track.x[1:])) < 1e-9 and np.max(np.abs(script.y - track.y[1:])) < 1e-9
        assert script.z is not None and script.pitch is not None
        assert np.array_equal(script.z, track.z[1:]) and np.allclose(script.pitch, track.pitch[1:], atol=1e-15)
    assert parsed.vehicle("hero").start_speed == 15.0


def test_a_scripted_vehicle_takes_its_height_and_pitch_from_its_script() -> None:
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.traffic import ScriptedMotion, Traffic

    road = load_map("highway")
    lane = int(np.argmax(road.length))
    traffic = Traffic(road, ["sedan", "sedan"], [lane, lane], [5.0, 40.0], [10.0, 10.0], [None, None],
                      [road.lanes[lane].successors[0]] * 2, np.random.default_rng(0), DT)
    lane_z = traffic.z_pitch()[0].copy()
    n = 3
    traffic.scripted = {1: ScriptedMotion(x=np.full(n, traffic.x[1]), y=np.full(n, traffic.y[1]),
                                          yaw=np.full(n, traffic.yaw[1]), speed=np.zeros(n),
                                          braking=np.zeros(n, bool), z=np.full(n, 7.5), pitch=np.full(n, 0.03))}
    assert traffic.z_pitch()[0][1] == lane_z[1]  # before the first step: the start, from the lane
    traffic.step(0)
    z, pitch = traffic.z_pitch()
    assert z[1] == 7.5 and pitch[1] == 0.03


def test_the_contact_pose_is_where_the_ego_met_the_vehicle() -> None:
    """Lite puts both vehicles back after a contact; the trace must keep where the ego met the other, or the
    file's vehicle stands a step short of the ego (a creep into it then meets it late or never)."""
    from genesis_rl.sim.interface import VehicleControl
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.traffic import AutopilotParams, Traffic

    road = load_map("highway")
    npc = AutopilotParams(8.0, 1.5, 2.0, 2.0, 3.0, 0.0, 0.0)
    lane = int(np.argmax(road.length))  # the longest lane: both stay on it
    traffic = Traffic(road, ["sedan", "sedan"], [lane, lane], [5.0, 12.0], [15.0, 1.0], [None, npc],
                      [road.lanes[lane].successors[0]] * 2, np.random.default_rng(0), DT)
    traffic.ego_control = VehicleControl(throttle=1.0)
    for k in range(40):
        before = traffic.x[1], traffic.y[1]
        hits = [c for c in traffic.step(k) if 0 in (c.vehicle_a, c.vehicle_b)]
        if hits:
            met = traffic.ego_contact_poses[1]
            assert (traffic.x[1], traffic.y[1]) == before  # put back ...
            assert np.hypot(met[0] - before[0], met[1] - before[1]) > 1e-3  # ... from where the ego met it
            break
        assert traffic.ego_contact_poses == {}
    else:
        pytest.fail("the ego never reached the vehicle ahead")
