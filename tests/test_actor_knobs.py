"""Actor knobs (issue 32): declared, rate limited at any step length, ODD conditions, lite kinematics."""

from __future__ import annotations

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.lite.actors import CUT_IN_DURATION, cut_in_offset, cut_in_start_gap, lead_speed
from genesis_rl.world.actor_knobs import (
    ACTOR_KNOBS,
    ActorKnobSpec,
    TrafficConditions,
    actor_max_deltas,
    cut_in_gap,
    limit_step,
    parse_traffic_conditions,
    register_actor_knob,
)
from genesis_rl.world.knobs import KNOBS


def test_tm_names_and_sources_are_declared_and_only_lead_decel_and_the_cut_in_are_turned():
    turned = ("lead_decel", "cut_in_ttc", "vehicle_percentage_speed_difference", "ignore_lights_percentage",
              "cut_in_relative_speed")
    for name in ("lead_decel", "lead_brake_onset", "cut_in_ttc", "cut_in_onset", "distance_to_leading_vehicle",
                 "vehicle_percentage_speed_difference", "ignore_lights_percentage", "auto_lane_change",
                 "random_left_lanechange_percentage", "random_right_lanechange_percentage"):
        assert name in ACTOR_KNOBS and ACTOR_KNOBS[name].source
        # only the knobs the step loop turns join the knob registry, as actor knobs at their harmless default
        assert (name in KNOBS) == (name in turned)
    spec = KNOBS["lead_decel"]
    assert spec.is_actor and spec.default == 0.0 and (spec.low, spec.high, spec.unit) == (0.0, 8.0, "m/s^2")
    assert spec.carla_field is None and not any(k.is_actor for n, k in KNOBS.items() if n not in turned)
    assert KNOBS["cut_in_ttc"].is_actor and KNOBS["cut_in_ttc"].carla_field is None
    assert "R157" in ACTOR_KNOBS["cut_in_ttc"].source and "CCRb" in ACTOR_KNOBS["lead_decel"].source


def test_register_actor_knob_and_refuses_a_clash():
    spec = register_actor_knob(ActorKnobSpec("test_ped_speed", 0.0, 3.0, "m/s", 1.4, 0.5))
    assert ACTOR_KNOBS["test_ped_speed"] is spec
    with pytest.raises(UserInputError, match="already declared"):
        register_actor_knob(ActorKnobSpec("test_ped_speed", 0.0, 4.0, "m/s", 1.4, 0.5))
    del ACTOR_KNOBS["test_ped_speed"]


@pytest.mark.parametrize("dt", [0.05, 0.2])
def test_natural_limit_holds_at_any_step_length(dt):
    """Pulling lead_decel from 0 to 8 m/s^2 takes 2 s at 4 m/s^2 per second, whatever the step."""
    values = {"lead_decel": 0.0, "cut_in_ttc": 10.0}
    t = 0.0
    while t < 1.0 - 1e-9:
        values = limit_step(values, {"lead_decel": 8.0, "cut_in_ttc": 0.4}, dt)
        t += dt
    assert values["lead_decel"] == pytest.approx(4.0)
    assert values["cut_in_ttc"] == pytest.approx(9.5)
    np.testing.assert_allclose(actor_max_deltas(["lead_decel"], dt), [4.0 * dt])


def test_braking_lead_speed_profile_matches_demand():
    dt, v, t, speeds = 0.05, 13.9, 0.0, []
    for _ in range(100):  # 5 s; brakes at 6 m/s^2 (CCRb) from t = 1.025 s (mid-step)
        v = lead_speed(v, t, 6.0, 1.025, dt)
        t += dt
        speeds.append(v)
    assert speeds[19] == pytest.approx(13.9)  # t = 1.0 s: not yet braking
    assert speeds[29] == pytest.approx(13.9 - 6.0 * (1.5 - 1.025))  # t = 1.5 s
    assert speeds[-1] == 0.0  # stopped by 1.025 + 13.9 / 6 = 3.34 s and never reverses


def test_cut_in_ends_in_ego_lane_with_declared_gap():
    ego_v, cut_v, ttc, lane = 25.0, 25.0 - 40 / 3.6, 1.18, 3.5  # R157's 40 km/h row
    gap0 = cut_in_start_gap(ego_v, cut_v, ttc)
    dt, t, onset = 0.05, 0.0, 2.0
    gap, lateral = gap0 + (ego_v - cut_v) * onset, []
    while t < onset + CUT_IN_DURATION - 1e-9:
        t += dt
        gap -= (ego_v - cut_v) * dt
        lateral.append(cut_in_offset(t, onset, lane))
    assert lateral[0] == pytest.approx(lane) and lateral[-1] == pytest.approx(0.0, abs=1e-9)
    assert all(b <= a + 1e-12 for a, b in zip(lateral, lateral[1:], strict=False))  # monotone into the lane
    assert gap == pytest.approx(cut_in_gap(ego_v, cut_v, ttc))
    assert gap / (ego_v - cut_v) == pytest.approx(1.18)


def test_traffic_conditions_parse_and_refuse_naming_field():
    cond = parse_traffic_conditions({"max_lead_decel": 2.0, "min_cut_in_ttc": 0.94})
    assert cond == TrafficConditions(2.0, 0.94)
    assert cond.contains({"lead_decel": 2.0, "cut_in_ttc": 1.0}) and not cond.contains({"lead_decel": 6.0})
    with pytest.raises(UserInputError, match="odd.traffic.max_lead_decel"):
        parse_traffic_conditions({"max_lead_decel": -1})
    with pytest.raises(UserInputError, match="odd.traffic.min_cut_in_ttc"):
        parse_traffic_conditions({"min_cut_in_ttc": "short"})
    with pytest.raises(UserInputError, match="unknown field"):
        parse_traffic_conditions({"max_decel": 3})


def test_weather_only_lite_episode_is_bit_identical_with_the_actor_knobs_at_their_defaults():
    """A seeded highway scene (200 ticks, throttle 0.3): setting every knob each tick, the actor knobs at their
    defaults, moves no vehicle by a single bit against ticking without them; the ego ends where it did on main
    at dc9ed91, before actor knobs. (A hash of every pose, which this test held before, changed with the
    numpy build: numpy 2.4.6 rounds some NPC's trigonometry differently, on main as well.)"""
    from genesis_rl.sim.interface import VehicleControl
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.world.knobs import Weather

    scene = generate_catalog("highway", 1, 3).scenes[0]

    def run(set_knobs: bool) -> np.ndarray:
        with LiteBackend().create_simulation(scene, seed=0, render=False) as sim:
            sim.apply_ego_control(VehicleControl(throttle=0.3))
            out = []
            for _ in range(200):
                if set_knobs:
                    sim.set_weather(Weather.default())
                sim.tick()
                out.append(sim.poses()[:, :2].copy())
            assert sim.actor_events() == []
        return np.array(out)

    plain, with_knobs = run(False), run(True)
    assert np.array_equal(plain, with_knobs)
    assert float(plain[-1, 0, 0]) == pytest.approx(55.8651522936967, abs=1e-9)
    assert float(plain[-1, 1, 0]) == pytest.approx(71.0090980840106, abs=1e-9)


@pytest.mark.parametrize("steps_per_s", [20, 10])
def test_forced_lead_braking_in_lite_traffic_follows_the_demand(steps_per_s):
    """On a crafted highway scene the ego's leader brakes at CCRb's 6 m/s^2 from 1.025 s: its speed falls
    by 6 m/s^2 after onset (within 1e-9), at two step lengths."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    scene = generate_catalog("highway", 1, 3).scenes[0]
    with LiteBackend().create_simulation(scene, seed=0, render=False) as sim:
        tr = sim.traffic
        tr.dt = 1.0 / steps_per_s
        lead = tr.lead()
        assert lead is not None
        tr.forced_braking = (lead.vehicle_id, 6.0, 1.025)
        v, t = [], []
        for _ in range(3 * steps_per_s):
            sim.tick()
            v.append(float(tr.v[lead.vehicle_id]))
            t.append(tr._episode_time)
    v0 = v[int(1.0 * steps_per_s) - 1]  # speed at t = 1.0 s, before onset
    at2 = v[2 * steps_per_s - 1]  # t = 2.0 s
    assert at2 == pytest.approx(max(0.0, v0 - 6.0 * (2.0 - 1.025)), abs=1e-9)


def test_lead_braking_switched_on_before_the_first_tick_brakes_the_car_in_the_egos_lane():
    """Before the first tick the ego's corridor is straight (it bends with the steering), so on a bend it runs
    through the next lane: in free-flow highway scene 2 of catalog seed 0 it finds vehicle 2 in the
    neighbouring lane, 16 m ahead, while vehicle 1 drives 36 m ahead in the ego's own lane. The knob must brake
    vehicle 1."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    scene = generate_catalog("highway", 3, 0, traffic="free_flow").scenes[2]
    with LiteBackend().create_simulation(scene, seed=scene.seed, render=False) as sim:
        tr = sim.traffic
        corridor = tr.lead()
        assert corridor is not None and corridor.vehicle_id == 2 and tr.lane[2] != tr.lane[0]
        tr.set_lead_braking(6.0)
        assert tr.braking_vehicle == 1 and tr.lane[1] == tr.lane[0]
        v1 = float(tr.v[1])
        for _ in range(20):
            sim.tick()
        assert float(tr.v[1]) == pytest.approx(v1 - 6.0 * 1.0, abs=0.5)  # it is the one slowing


def test_odd_file_traffic_table_is_read_and_bad_values_exit_2(tmp_path):
    import subprocess
    import sys

    from genesis_rl.world.odd.domain import parse_odd

    odd = parse_odd({"name": "hw", "traffic": {"max_lead_decel": 2.0, "min_cut_in_ttc": 1.18}}, "hw.toml")
    assert odd.traffic == TrafficConditions(2.0, 1.18)
    assert odd.describe()["traffic"] == {"max_lead_decel": 2.0, "min_cut_in_ttc": 1.18}
    assert "traffic" not in parse_odd({"name": "hw"}, "hw.toml").describe()  # as before without a table
    with pytest.raises(UserInputError, match=r"ODD 'hw.toml': traffic.min_cut_in_ttc"):
        parse_odd({"name": "hw", "traffic": {"min_cut_in_ttc": 0.1}}, "hw.toml")
    code = ("from genesis_rl.core.errors import UserInputError\n"
            "from genesis_rl.world.odd.domain import parse_odd\n"
            "try:\n    parse_odd({'name': 'x', 'traffic': {'max_lead_decel': 99}}, 'x.toml')\n"
            "except UserInputError as e:\n    print(e); raise SystemExit(e.exit_code)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert run.returncode == 2 and "traffic.max_lead_decel" in run.stdout


def test_forced_cut_in_in_lite_traffic_ends_centred_in_the_ego_lane():
    """Vehicle 2 of a seeded highway scene drives 3.5 m beside the ego's lane, 16 m ahead; told to cut in at
    0.5 s it takes the ego's lane and pure pursuit steers it across: 3.5 m to go before, < 0.1 m after 5 s."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    scene = generate_catalog("highway", 1, 3).scenes[0]
    with LiteBackend().create_simulation(scene, seed=0, render=False) as sim:
        tr = sim.traffic
        c, s = np.cos(tr.yaw[0]), np.sin(tr.yaw[0])

        def lateral() -> float:
            return float(-(tr.x[2] - tr.x[0]) * s + (tr.y[2] - tr.y[0]) * c)

        assert tr.lane[2] != tr.lane[0] and lateral() == pytest.approx(-3.5, abs=0.01)
        tr.forced_cut_in = (2, 0.5)
        path = []
        for _ in range(100):
            sim.tick()
            path.append(lateral())
    assert tr.lane[2] == tr.lane[0]
    assert path[9] == pytest.approx(-3.5, abs=0.01)  # before onset: in its own lane
    assert abs(path[-1]) < 0.1
    assert all(b >= a - 1e-6 for a, b in zip(path, path[1:], strict=False))  # moves steadily across
