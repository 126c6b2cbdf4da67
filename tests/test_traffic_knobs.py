"""The surrounding traffic's behaviour and the cut-in on both backends (issue 32): two of CARLA
TrafficManager's per-vehicle parameters on lite's traffic model, and the traffic manager calls that realise the
cut-in and those parameters on a CARLA server (offline: a recording traffic manager)."""

from __future__ import annotations

import numpy as np
import pytest

from genesis_rl.world.actor_knobs import CUT_IN_PERCEIVE_AFTER_S, pick_cut_in
from genesis_rl.world.knobs import KNOBS


def _highway_sim(scene_index: int = 0):
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    scene = generate_catalog("highway", 4, 3).scenes[scene_index]
    return LiteBackend().create_simulation(scene, seed=0, render=False)


def test_the_tm_knobs_are_knobs_of_the_env_at_harmless_defaults():
    from genesis_rl.sim.lite.backend import LiteBackend

    for name in ("vehicle_percentage_speed_difference", "ignore_lights_percentage"):
        spec = KNOBS[name]
        assert spec.is_actor and spec.default == 0.0 and name in LiteBackend.actor_knobs
    assert (KNOBS["vehicle_percentage_speed_difference"].low, KNOBS["vehicle_percentage_speed_difference"].high) == (
        -50.0, 100.0)


def test_speed_difference_scales_every_npcs_target_speed_and_not_the_egos():
    sim = _highway_sim()
    try:
        tr = sim.traffic
        base, wander = tr.v0_base.copy(), tr.v0 - tr.v0_base
        tr.set_traffic_behaviour(30.0, 0.0)  # TM: 30 % below each one's own target
        npc = tr.is_npc
        assert np.allclose(tr.v0_base[npc], 0.7 * base[npc]) and tr.v0_base[0] == base[0]
        assert np.allclose((tr.v0 - tr.v0_base)[npc], wander[npc])  # each keeps its wander around the target
        for _ in range(400):  # 20 s: the traffic settles toward its slower targets
            sim.tick()
        moving = npc & (tr.stop_timer <= 0)
        assert np.median(tr.v[moving] / base[moving]) < 0.8
        tr.set_traffic_behaviour(0.0, 0.0)
        assert np.allclose(tr.v0_base, base)
    finally:
        sim.destroy()


def _red_runs(pct: float, steps: int = 1200) -> tuple[int, int]:
    """(NPCs that entered a junction connector on red, lane entries with a red-runner drawn) on an urban scene."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.sim.lite.traffic import RED

    scene = generate_catalog("urban", 2, 3).scenes[1]
    sim = LiteBackend().create_simulation(scene, seed=0, render=False)
    tr = sim.traffic
    try:
        tr.set_traffic_behaviour(0.0, pct)
        ran, drawn = set(), 0
        for _ in range(steps):
            lane_before = tr.lane.copy()
            phase = tr._signal_phases(tr.time)
            sig = tr._lane_sig_j[lane_before]
            red = np.array([sig[i] >= 0 and phase[sig[i], tr._lane_sig_g[lane_before[i]]] == RED
                            for i in range(tr.n)])
            sim.tick()
            entered = (tr.lane != lane_before) & tr.is_npc
            drawn += int(tr.runs_red[entered].sum())
            for i in np.flatnonzero(entered & red & (tr._conn_j[tr.lane] >= 0)):
                ran.add(int(i))
        return len(ran), drawn
    finally:
        sim.destroy()


def test_ignore_lights_makes_npcs_run_red_lights_and_its_default_draws_nothing():
    ran, drawn = _red_runs(0.0)
    assert ran == 0 and drawn == 0
    ran, drawn = _red_runs(100.0)
    assert drawn > 0 and ran >= 1


def test_the_tm_knobs_at_their_defaults_change_no_bit_of_an_episode():
    def poses(set_knobs: bool) -> np.ndarray:
        sim = _highway_sim(1)
        try:
            out = []
            for _ in range(200):
                if set_knobs:
                    sim.traffic.set_traffic_behaviour(0.0, 0.0)
                sim.tick()
                out.append(sim.poses()[:, :2].copy())
            return np.array(out)
        finally:
            sim.destroy()

    assert np.array_equal(poses(False), poses(True))


def test_one_rule_picks_the_car_to_cut_in_on_every_backend():
    cands = [(3, 30.0, 10.0), (4, 8.0, 3.0), (5, 0.5, 2.0), (6, 6.0, 0.3), (7, 5.5, 2.0)]
    # the knob is the time-to-collision once the cut-in is perceivable, 0.3 s after it starts: 2.7 s asks for a
    # gap closing in 3.0..2.75 s now, vehicle 3 (3.0 s) and 7 (2.75 s); the nearer wins
    assert CUT_IN_PERCEIVE_AFTER_S == 0.3
    assert pick_cut_in(cands, 2.7) == (7, 5.5, 2.0)
    assert pick_cut_in(cands, 2.3) is None  # 2.35..2.6 s now: nobody there (4 is at 2.67 s)
    assert pick_cut_in(cands, 2.4) == (4, 8.0, 3.0)  # too close (0.5 m) and not closing (0.3 m/s) never count


class _RecordingTM:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def __getattr__(self, name: str):
        return lambda *a: self.calls.append((name, *a))


def test_on_carla_the_cut_in_asks_the_traffic_manager_to_move_the_car_over_and_follows_it():
    from genesis_rl.sim.carla.actor_control import CutIn, Neighbour

    tm, cut = _RecordingTM(), CutIn()
    actors = {4: "actor4", 7: "actor7"}
    offsets = {4: 3.5, 7: 3.5}
    near = [Neighbour(4, 20.0, 2.0, True), Neighbour(7, 9.0, 3.0, False)]  # 10 s and 3 s away
    cut.step(tm, 10.0, 10.0, 0.0, lambda: near, actors.get, offsets.get)  # at its default: nothing
    cut.step(tm, 5.0, 10.0, 0.05, lambda: near, actors.get, offsets.get)  # nobody within 4.75..5 s once seen
    assert tm.calls == [] and cut.events() == []
    cut.step(tm, 3.0, 10.0, 0.10, lambda: near, actors.get, offsets.get)  # 3 s now is 2.7 s once perceivable
    assert tm.calls == [] and cut.events() == []
    cut.step(tm, 2.7, 10.0, 0.10, lambda: near, actors.get, offsets.get)  # R157's measure: 2.7 s once seen
    assert tm.calls == [("force_lane_change", "actor7", False)]  # in the right lane: it moves left
    offsets[7] = 3.2  # wandered 0.3 m: not yet perceivable
    cut.step(tm, 2.7, 10.0, 0.15, lambda: near, actors.get, offsets.get)
    offsets[7] = 3.0  # 0.5 m: perceivable now
    cut.step(tm, 2.7, 10.0, 0.20, lambda: near, actors.get, offsets.get)
    assert len(tm.calls) == 1  # one cut-in at a time
    (e,) = cut.events()
    assert (e.kind, e.vehicle_id, e.onset_s, e.perceivable_s) == ("cut_in", 7, 0.10, 0.20)
    assert e.ttc_s == pytest.approx(3.0) and e.gap_m == 9.0 and e.closing_m_s == 3.0
    assert e.perceived_ttc_s == pytest.approx((9.0 - 3.0 * 0.1) / 3.0)  # projected from the onset to 0.20 s
    offsets[7] = 0.3  # in the ego's lane: over, the next one may come
    near = [Neighbour(4, 5.8, 2.0, True)]
    cut.step(tm, 2.7, 10.0, 0.25, lambda: near, actors.get, offsets.get)
    assert tm.calls[-1] == ("force_lane_change", "actor4", True) and cut.vehicle == 4


def test_on_carla_the_traffic_behaviour_goes_to_the_traffic_manager_for_every_npc_when_it_changes():
    from genesis_rl.sim.carla.actor_control import TrafficBehaviour

    tm, tb = _RecordingTM(), TrafficBehaviour()
    values = {"vehicle_percentage_speed_difference": 0.0, "ignore_lights_percentage": 0.0}
    assert tb.apply(tm, values, ["a", "b"]) == [] and tm.calls == []  # the defaults: nothing sent
    values["ignore_lights_percentage"] = 40.0
    assert tb.apply(tm, values, ["a", "b"]) == ["ignore_lights_percentage"]
    assert tm.calls == [("ignore_lights_percentage", "a", 40.0), ("ignore_lights_percentage", "b", 40.0)]
    assert tb.apply(tm, values, ["a", "b"]) == [] and len(tm.calls) == 2  # unchanged: not sent again


def test_path_offset_is_the_distance_from_a_polyline():
    from genesis_rl.sim.carla.lead import path_offset

    path = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 10.0]])
    assert path_offset(path, np.array([5.0, 3.5])) == pytest.approx(3.5)
    assert path_offset(path, np.array([15.0, 5.0])) == pytest.approx(0.0, abs=1e-12)
    assert path_offset(path[:1], np.array([0.0, 1.0])) is None


def test_a_carla_backend_now_realises_the_cut_in_and_the_traffic_knobs():
    pytest.importorskip("carla")
    from genesis_rl.sim.carla.backend import CarlaBackend

    for name in ("lead_decel", "cut_in_ttc", "vehicle_percentage_speed_difference", "ignore_lights_percentage"):
        assert name in CarlaBackend.actor_knobs


def test_on_carla_a_neighbour_gets_ready_at_the_relative_speed_and_is_let_go_at_the_default():
    """``cut_in_relative_speed``: the nearest neighbour ahead is given a desired speed that much under the ego's
    (km/h, the traffic manager's unit) but not under half its speed limit, the cutter keeps the speed it crosses
    at, and at the knob's default each vehicle held gets the traffic's speed difference back (which clears a
    desired speed in CARLA's TM)."""
    from genesis_rl.sim.carla.actor_control import CutIn, Neighbour

    class _Car:
        def __init__(self, name: str) -> None:
            self.name = name

        def get_speed_limit(self) -> float:
            return 90.0  # km/h: 25 m/s, so never slowed under 12.5 m/s

        def __eq__(self, other: object) -> bool:
            return other == self.name

    tm, cut = _RecordingTM(), CutIn()
    actors, offsets = {4: _Car("actor4"), 7: _Car("actor7")}, {4: 3.5, 7: 3.5}
    near = [Neighbour(4, 40.0, 0.0, True), Neighbour(7, 25.0, 0.1, False)]  # the traffic's pace: nothing closes

    def step(t: float, ttc: float = 1.64, rel: float = 6.0, ego: float = 20.0) -> None:
        cut.step(tm, ttc, 10.0, t, lambda: near, actors.get, offsets.get, rel, ego, 15.0)

    step(0.0, rel=0.0)
    assert tm.calls == [] and cut.preparing == -1  # at 0 the traffic alone decides, as before
    step(0.05)
    assert tm.calls == [("set_desired_speed", "actor7", pytest.approx(3.6 * 14.0))] and cut.preparing == 7
    step(0.10, ego=20.1)  # within a quarter of a m/s: not sent again
    assert len(tm.calls) == 1
    step(0.15, rel=12.0)  # 8 m/s wanted, 12.5 m/s at least: half its speed limit
    assert tm.calls[-1] == ("set_desired_speed", "actor7", pytest.approx(3.6 * 12.5))
    near = [Neighbour(4, 40.0, 0.0, True), Neighbour(7, 14.4, 8.0, False)]  # 1.8 s, 1.5 s once seen: R157's window
    step(0.20)
    assert tm.calls[-2:] == [("force_lane_change", "actor7", False), ("set_desired_speed", "actor7",
                                                                      pytest.approx(3.6 * 12.0))]
    assert cut.held == {7: pytest.approx(12.0)} and cut.preparing == -1
    (e,) = cut.events()
    assert e.closing_m_s == 8.0 and e.ttc_s == pytest.approx(1.8)
    offsets[7] = 0.2
    step(0.25, ttc=10.0)  # the knob back at its default: let go
    assert tm.calls[-1] == ("vehicle_percentage_speed_difference", "actor7", 15.0) and cut.held == {}
    assert not cut.wanted(10.0, 10.0)


def test_the_odd_bounds_the_cut_ins_relative_speed_and_names_the_field(tmp_path):
    from genesis_rl.core.errors import UserInputError
    from genesis_rl.world.actor_knobs import TrafficConditions, parse_traffic_conditions

    assert TrafficConditions().max_cut_in_relative_speed == pytest.approx(16.67, abs=0.01)  # R157: 60 km/h
    tc = parse_traffic_conditions({"max_cut_in_relative_speed": 5.0})
    assert tc.violations({"cut_in_relative_speed": 6.0}) == ["cut_in_relative_speed 6 m/s > 5"]
    assert tc.contains({"cut_in_relative_speed": 5.0}) and tc.contains({})
    with pytest.raises(UserInputError, match="max_cut_in_relative_speed"):
        parse_traffic_conditions({"max_cut_in_relative_speed": 25.0})
