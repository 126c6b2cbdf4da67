"""The cut-in as a knob of the env and the careful-driver reference that blames actor-made collisions (issue 32).

The cut-in moves a neighbour into the ego's lane at the time-to-collision the knob asks for; the reference
(UN R157's competent and careful driver) is checked by hand on a braking lead; a cut-in no careful driver
could avoid is labelled unavoidable, and one a careful driver avoids is the system's failure.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from genesis_rl.labels.blame import VISIBILITY_REFERENCE, blame_label, reference_name
from genesis_rl.labels.careful_driver import R157, careful_driver_evidence, event_for_collision
from genesis_rl.sim.interface import ActorEvent
from genesis_rl.world.actor_knobs import CUT_IN_PERCEIVE_AFTER_S
from genesis_rl.world.knobs import KNOBS
from genesis_rl.world.step_record import CollisionStep, EgoStep, LeadStep, PerceptionStep, StepRecord

DT = 0.05


def _record(i: int, ego_speed: float, gap: float, lead_speed: float, lead_id: int, hit: bool) -> StepRecord:
    return StepRecord(step=i + 1, time_s=round((i + 1) * DT, 3), ego=EgoStep(ego_speed, 0.0, 0.0, 0.0, "cruise"),
                      lead=LeadStep(lead_id, max(gap, 0.0), lead_speed, math.nan, None),
                      perception=PerceptionStep(0, 0, 0.0, (), ()),
                      collision=CollisionStep(hit, ego_speed if hit else 0.0, lead_id if hit else -1), knobs={})


def _blind_ego_behind_a_braking_lead(gap0: float, decel: float = 6.0, onset: float = 1.0,
                                     speed: float = 20.0) -> list[StepRecord]:
    """An ego that never brakes, at ``speed``, behind a lead (vehicle 5) at ``gap0`` and the same speed that
    brakes at ``decel`` from ``onset``: records until the gap closes (the impact)."""
    out = []
    for i in range(2000):
        t = (i + 1) * DT
        tb = max(0.0, t - onset)
        stop = speed / decel
        lead_v = max(0.0, speed - decel * tb)
        lead_x = speed * min(t, onset) + (speed * min(tb, stop) - 0.5 * decel * min(tb, stop) ** 2)
        gap = gap0 + lead_x - speed * t
        out.append(_record(i, speed, gap, lead_v, 5, gap <= 0.0))
        if gap <= 0.0:
            return out
    raise AssertionError("no impact")


def test_the_careful_driver_is_checked_by_hand_on_a_braking_lead():
    """Both at 20 m/s, the lead brakes at 6 m/s^2 from 1 s. The careful driver brakes 0.4 + 0.75 s after the
    onset, reaches 7.59 m/s^2 in 0.6 s: it needs 23 + 11.54 + 20.69 = 55.24 m to stop, the lead needs 33.33 m.
    From 30 m it stops 8.1 m short of the lead; from 15 m it hits it."""
    braking = ActorEvent("lead_braking", 5, 1.0, 1.0)
    far = _blind_ego_behind_a_braking_lead(30.0)
    ev = careful_driver_evidence(far, len(far) - 1, braking, DT)
    # 1.5 s of headway is critical (under 2 s) as soon as the 0.4 s of perception are over
    assert ev["reference"] == R157.name and ev["critical_s"] == pytest.approx(1.4)
    assert ev["brake_from_s"] == pytest.approx(2.15)
    assert not ev["collides"] and ev["min_gap_m"] == pytest.approx(30.0 + 33.33 - 55.24, abs=0.15)
    near = _blind_ego_behind_a_braking_lead(15.0)
    ev = careful_driver_evidence(near, len(near) - 1, braking, DT)
    assert ev["collides"] and ev["collision_s"] > near[-1].time_s  # it hits later and slower than the blind ego
    # the first event with the vehicle hit counts (a driver has watched it since); another vehicle's does not
    events = [ActorEvent("cut_in", 7, 0.5, 0.9), braking, ActorEvent("lead_braking", 5, 1.5, 1.5)]
    assert event_for_collision(events, near, len(near) - 1) == braking


def test_a_braking_lead_is_critical_once_perceived_so_a_longer_gap_never_costs_the_careful_driver():
    """A lead braking to a stop is critical from its brake lights on: the careful driver reacts 0.4 + 0.75 s after
    the onset whatever the gap, so a driver that avoided the lead from some gap avoids it from every longer one.
    Gated on the headway (as cut-ins are), it had held its speed from 50-70 m until the headway fell under 2 s
    and then hit a lead braking at 6 m/s^2, which it avoided from 30 m."""
    braking = ActorEvent("lead_braking", 5, 1.0, 1.0)
    for decel in (1.0, 3.0, 6.0):
        verdicts = []
        for gap0 in (10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0):
            records = _blind_ego_behind_a_braking_lead(gap0, decel=decel)
            ev = careful_driver_evidence(records, len(records) - 1, braking, DT)
            assert ev["critical_s"] == pytest.approx(1.4) and ev["brake_from_s"] == pytest.approx(2.15)
            verdicts.append(ev["collides"])
        assert verdicts == sorted(verdicts, reverse=True), (decel, verdicts)  # collides, ..., then avoids for good
        assert verdicts[-1] is False and (decel < 6.0 or verdicts[0] is True)
    # the old gate's case: from 60 m (3 s at 20 m/s) behind a lead braking at 6 m/s^2 it now keeps about 38 m
    records = _blind_ego_behind_a_braking_lead(60.0)
    ev = careful_driver_evidence(records, len(records) - 1, braking, DT)
    assert not ev["collides"] and ev["min_gap_m"] == pytest.approx(60.0 + 33.33 - 55.24, abs=0.15)
    # a cut-in is still gated: far ahead and closing slowly, it is not critical when perceived
    assert not R157.critical(60.0, 20.0, 19.0) and R157.critical(30.0, 20.0, 19.0)


def test_blame_with_a_careful_driver_reference_never_calls_an_avoidable_collision_unavoidable():
    unseen = {"visible": False, "stoppable": False, "too_fast_for_visibility_m_s": 0.0}
    assert blame_label(unseen, oracle_collides=True) == "unavoidable"  # the visibility reference, as before
    avoided = {"reference": R157.name, "collides": False}
    assert blame_label(unseen, True, avoided) == "control"
    assert blame_label(unseen, False, avoided) == "perception"
    assert blame_label({"stoppable": True}, True, {"reference": R157.name, "collides": True}) == "unavoidable"
    assert reference_name(avoided) == R157.name and reference_name(None) == VISIBILITY_REFERENCE


def test_the_cut_in_is_a_knob_of_the_env_that_lite_realises():
    from genesis_rl.sim.lite.backend import LiteBackend

    spec = KNOBS["cut_in_ttc"]
    assert spec.is_actor and spec.default == 10.0 and (spec.low, spec.high, spec.unit) == (0.4, 10.0, "s")
    assert "cut_in_ttc" in LiteBackend.actor_knobs


def _cut_in_on_lite(knob: float, steps: int = 120):
    """Seeded highway scene 3 of 4, the ego on lite's autopilot at up to 16 m/s, the knob held at ``knob``."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    scene = generate_catalog("highway", 4, 3).scenes[3]
    sim = LiteBackend().create_simulation(scene, seed=0, render=False)
    tr = sim.traffic
    tr.drive_ego_on_autopilot(16.0)
    lanes = []
    for _ in range(steps):
        tr.set_cut_in(knob, KNOBS["cut_in_ttc"].default)
        sim.tick()
        lanes.append(int(tr.lane[2]))
    return sim, tr, lanes


def test_a_neighbour_cuts_in_at_the_time_to_collision_the_knob_asks_for():
    """Vehicle 2 drives slower than the ego one lane over: asked for 3 s, it starts across when the gap ahead
    of the ego closes to 3 s, and ends in the ego's lane."""
    sim, tr, lanes = _cut_in_on_lite(3.0)
    try:
        events = sim.actor_events()
        assert len(events) == 1
        e = events[0]
        assert e.kind == "cut_in" and e.vehicle_id == 2 and lanes[0] != tr.lane[0]
        # the knob is R157's time-to-collision, once the cut-in is perceivable: the onset comes that much sooner
        assert 3.0 - 0.25 <= e.ttc_s - CUT_IN_PERCEIVE_AFTER_S <= 3.0
        assert e.ttc_s == pytest.approx(e.gap_m / e.closing_m_s)
        assert e.gap_m > 1.0 and e.closing_m_s > 0.5
        # R157's careful driver perceives it once it has wandered 0.375 m: after the onset, within a second
        assert e.perceivable_s is not None and 0.0 < e.perceivable_s - e.onset_s < 1.0
        assert tr.lane[2] == tr.lane[0]
    finally:
        sim.destroy()
    sim, tr, lanes = _cut_in_on_lite(KNOBS["cut_in_ttc"].default)  # at its default the knob asks for nothing
    try:
        assert sim.actor_events() == [] and set(lanes) == {lanes[0]} and lanes[0] != tr.lane[0]
    finally:
        sim.destroy()


def test_the_odd_holds_the_cut_in_at_its_shortest_time_to_collision_and_labels_beyond_it(tmp_path):
    from test_actor_env import odd_with_traffic

    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

    odd = odd_with_traffic(tmp_path, min_cut_in_ttc=3.0)
    for keep_inside in (True, False):
        env = GenesisEnv(EnvConfig(map="highway", scenes=4, knobs=("fog_density", "cut_in_ttc"), dynamics="natural",
                                   observation="features", episode_steps=400, odd=odd, odd_keep_inside=keep_inside))
        try:
            env.reset(seed=0, options={"scene": 1, "episode_seed": 3})
            knob = []
            for _ in range(400):
                *_, info = env.step(np.array([0.0, -1.0], np.float32))
                knob.append(info["knobs"]["cut_in_ttc"])
            status = [r.odd_status for r in env.records]
        finally:
            env.close()
        assert knob[0] == pytest.approx(10.0 - 0.025, abs=1e-9)  # natural rate 0.5 s per s: 0.025 per step
        if keep_inside:
            assert min(knob) == pytest.approx(3.0, abs=0.01) and "outside" not in status
        else:  # a step is outside exactly when the knob asks for a shorter cut-in than the ODD releases
            assert min(knob) == pytest.approx(0.4) and status[-1] == "outside"
            assert all((s == "outside") == (k < 3.0) for k, s in zip(knob, status, strict=True))


def _blind_cut_in_episode(scene: int, lower_steps: int = 200) -> tuple[list[StepRecord], list[ActorEvent], int | None]:
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

    env = GenesisEnv(EnvConfig(map="highway", scenes=20, knobs=("fog_density", "cut_in_ttc"), dynamics="paper",
                               observation="features", episode_steps=200, system="blind"))
    try:
        env.reset(seed=0, options={"scene": scene, "episode_seed": scene})
        for k in range(200):  # the knob lowered for ``lower_steps`` steps (5 % of its range each), then held
            *_, info = env.step(np.array([-1.0, -1.0 if k < lower_steps else 0.0], np.float32))
            if info["collision"]:
                return list(env.records), env.actor_events(), len(env.records) - 1
        return list(env.records), env.actor_events(), None
    finally:
        env.close()


def test_an_unavoidable_cut_in_is_labelled_unavoidable_and_an_avoidable_one_is_the_systems():
    """A system that never brakes (``blind``) on two seeded highway scenes: in scene 1, the knob lowered all the
    way, the neighbour cuts 2 m ahead (0.35 s to collision once perceivable) and the careful driver hits it
    too; in scene 18, the knob lowered to 2.8 s, it cuts in 6 m ahead (2.8 s once perceivable, 2 m/s closing)
    and the careful driver stops short of it."""
    from genesis_rl.labels.distinct import what_was_hit

    for scene, lower_steps, unavoidable in ((1, 200, True), (18, 15, False)):
        records, events, hit_at = _blind_cut_in_episode(scene, lower_steps)
        assert hit_at is not None
        event = event_for_collision(events, records, hit_at)
        assert event is not None and event.kind == "cut_in"
        assert what_was_hit(records, hit_at, DT, events) == "cut in by the tester"
        careful = careful_driver_evidence(records, hit_at, event, DT)
        assert careful["collides"] == unavoidable
        blame = blame_label({"stoppable": True}, True, careful)
        assert blame == ("unavoidable" if unavoidable else "control")


def test_with_the_cut_in_the_agent_also_observes_the_neighbour_a_tester_would_cut_in():
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
    from genesis_rl.env.observation import (
        ACTOR_FEATURES,
        FEATURES,
        GAP_SCALE,
        NEIGHBOUR_FEATURES,
        SPEED_SCALE,
        actor_feature_names,
        feature_size,
    )

    assert actor_feature_names(("fog_density", "lead_decel")) == ACTOR_FEATURES  # as before the cut-in
    assert actor_feature_names(("fog_density",)) == ()
    env = GenesisEnv(EnvConfig(map="highway", scenes=4, knobs=("fog_density", "cut_in_ttc"), observation="features",
                               episode_steps=20))
    try:
        obs, _ = env.reset(seed=0, options={"scene": 3, "episode_seed": 0})
        n = feature_size(2, ACTOR_FEATURES + NEIGHBOUR_FEATURES)
        assert obs.shape == (env.config.obs_history * n,)
        neighbour = env._sim.neighbour_ahead()  # type: ignore[union-attr]
        assert neighbour is not None and neighbour.vehicle_id == 2  # the car of the cut-in test above
        row = obs[-n:]
        at = 2 + len(FEATURES) + len(ACTOR_FEATURES)
        ego_speed = env._sim.ego().speed  # type: ignore[union-attr]
        assert row[at] == pytest.approx(neighbour.gap / GAP_SCALE, abs=1e-6)
        assert row[at + 1] == pytest.approx(0.5 + 0.5 * (ego_speed - neighbour.speed) / SPEED_SCALE, abs=1e-6)
    finally:
        env.close()


def _prepared_cut_in(relative_speed: float, steps: int = 400, release_at: int | None = None):
    """Seeded highway scene 2 of 8 (its traffic keeps the ego's pace: no gap closes on its own), the ego on
    lite's autopilot at up to 22 m/s, a cut-in asked at R157's 1.64 s with ``relative_speed``; speeds,
    accelerations and lanes of every vehicle per step, and the speed caps the knob set."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    scene = generate_catalog("highway", 8, 3).scenes[2]
    sim = LiteBackend().create_simulation(scene, seed=0, render=False)
    tr = sim.traffic
    tr.drive_ego_on_autopilot(22.0)
    speeds, accels, lanes, caps = [], [], [], []
    for k in range(steps):
        ttc = KNOBS["cut_in_ttc"].default if release_at is not None and k >= release_at else 1.64
        tr.set_cut_in(ttc, KNOBS["cut_in_ttc"].default, relative_speed)
        sim.tick()
        speeds.append(tr.v.copy())
        accels.append(tr.accel.copy())
        lanes.append(tr.lane.copy())
        caps.append(dict(tr.cut_in_speed_caps))
    events = sim.actor_events()
    sim.destroy()
    return tr, events, np.array(speeds), np.array(accels), np.array(lanes), caps


def test_a_neighbour_gets_ready_at_the_relative_speed_asked_so_a_short_cut_in_can_come():
    """Without ``cut_in_relative_speed`` no gap in this scene closes and no cut-in comes. At 10 m/s the nearest
    neighbour ahead slows (never harder than its comfortable deceleration, never under half its own target
    speed) until its gap closes to R157's 1.64 s, crosses, and then holds the speed it crossed at."""
    from genesis_rl.world.actor_knobs import CUT_IN_SPEED_FLOOR

    _, events, *_ = _prepared_cut_in(0.0)
    assert events == []
    tr, events, speeds, accels, lanes, caps = _prepared_cut_in(10.0)
    assert events and events[0].vehicle_id == 2
    assert events[0].closing_m_s > 2.0  # the traffic alone gave none
    for e in events:
        assert 1.64 - 0.25 <= e.ttc_s - CUT_IN_PERCEIVE_AFTER_S <= 1.64
        assert e.ttc_s == pytest.approx(e.gap_m / e.closing_m_s)
        # measured where R157 measures it (the cutter 0.375 m across): within 0.1 s of the window asked
        assert 1.64 - 0.25 - 0.1 <= e.perceived_ttc_s <= 1.64 + 0.1
    _, _, _, accels_alone, _, _ = _prepared_cut_in(0.0, steps=20)
    e = events[0]
    i, k = e.vehicle_id, round(e.onset_s / DT) - 1
    # in the first second the scene's own gaps settle (IDM brakes as hard without the knob)
    np.testing.assert_allclose(accels[:4, i], accels_alone[:4, i])
    assert accels[20:k, i].min() >= -tr.b_comf[i] - 1e-9  # it got ready braking comfortably, not hard
    assert speeds[k, i] < speeds[0, i] - 3.0  # and it did slow
    for c in caps[:k]:  # the floor: half its own target speed
        assert c[i] >= CUT_IN_SPEED_FLOOR * tr.v0_base[i] - 1e-9
    _, _, _, _, _, caps_far = _prepared_cut_in(20.0, steps=10)  # asked for more than the floor allows
    assert caps_far[-1][i] == pytest.approx(CUT_IN_SPEED_FLOOR * tr.v0_base[i])
    in_lane = np.nonzero(lanes[k:, i] == lanes[k:, 0])[0]
    assert len(in_lane) > 20
    held = speeds[k + in_lane[0]:k + in_lane[0] + 20, i]
    # it keeps the speed it crossed at: never faster, slower only for its own leader (IDM)
    assert held.max() <= tr.cut_in_speed_caps[i] + 1e-9 and np.median(held) == pytest.approx(held[0], abs=0.3)


def test_with_the_knob_back_at_its_default_every_vehicle_held_drives_on():
    tr, events, speeds, *_ = _prepared_cut_in(10.0, steps=300, release_at=200)
    assert events and tr.cut_in_speed_caps == {}
    i = events[-1].vehicle_id
    assert speeds[-1, i] > speeds[199, i] + 1.0  # released, it speeds up again toward its own target


def test_a_car_standing_at_an_angle_with_a_corner_in_the_egos_path_is_its_lead():
    """The ego's lead is measured by the other car's turned body: 15 m ahead, its centre 2.4 m to the side, a
    car parallel to the ego is beside its path, the same car turned 0.35 rad toward it (a cut-in halfway) puts
    its front corner in the path."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    sim = LiteBackend().create_simulation(generate_catalog("highway", 4, 3).scenes[0], seed=0, render=False)
    try:
        tr = sim.traffic
        tr.steer_angle[:] = 0.0
        far = np.hypot(tr.x - tr.x[0], tr.y - tr.y[0]) > 200.0
        tr.x[1:] = np.where(far[1:], tr.x[1:], tr.x[0] + 1e4)  # everyone else out of the way
        c, s = np.cos(tr.yaw[0]), np.sin(tr.yaw[0])
        j = 1
        tr.x[j] = tr.x[0] + 15.0 * c + 2.4 * s  # 15 m ahead, 2.4 m to the right
        tr.y[j] = tr.y[0] + 15.0 * s - 2.4 * c
        tr.yaw[j] = tr.yaw[0]
        assert tr.lead() is None
        tr.yaw[j] = tr.yaw[0] + 0.35  # turned toward the ego's lane
        lead = tr.lead()
        assert lead is not None and lead.vehicle_id == j
        # the gap is to its nearest corner, not to where its rear bumper would be if it drove parallel
        half_lon = 0.5 * (tr.length[j] * np.cos(0.35) + tr.width[j] * np.sin(0.35))
        assert lead.gap == pytest.approx(15.0 - 0.5 * tr.length[0] - half_lon)
    finally:
        sim.destroy()


def test_a_cut_in_stopped_half_across_is_in_the_path_so_the_careful_driver_avoids_it():
    """Scene 13: the neighbour cuts in 5.4 s ahead (once perceivable), stops half across for the traffic
    ahead and a red light, and the blind system drives into its front corner. The careful driver saw it in its
    path and stops 3.6 m short: the collision is the system's, not unavoidable (0.24 called it a side impact
    no braking avoids, since lite's lead test measured the turned car as if it drove parallel)."""
    records, events, hit_at = _blind_cut_in_episode(13)
    assert hit_at is not None
    event = event_for_collision(events, records, hit_at)
    assert event is not None and event.kind == "cut_in" and event.perceived_ttc_s > 5.0
    assert any(r.lead.vehicle_id == event.vehicle_id for r in records[:hit_at])
    careful = careful_driver_evidence(records, hit_at, event, DT)
    assert not careful["collides"] and careful["min_gap_m"] > 3.0
    assert blame_label({"stoppable": True}, True, careful) == "control"


def test_a_lead_braking_while_the_cutter_crosses_does_not_hide_the_cut_ins_perceivable_moment():
    """0.24 marked only the latest event, so a lead braked by the tester during a cut-in left the cut-in
    never perceivable (and its careful driver without a moment to start from)."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog

    sim = LiteBackend().create_simulation(generate_catalog("highway", 4, 3).scenes[3], seed=0, render=False)
    try:
        tr = sim.traffic
        tr.drive_ego_on_autopilot(16.0)
        for _ in range(120):
            tr.set_cut_in(3.0, KNOBS["cut_in_ttc"].default)
            if sim.actor_events() and len(sim.actor_events()) == 1:
                tr.set_lead_braking(2.0)  # the step the cut-in starts, the lead brakes too
            sim.tick()
        kinds = [e.kind for e in sim.actor_events()]
        assert kinds[:2] == ["cut_in", "lead_braking"]
        cut = sim.actor_events()[0]
        assert cut.perceivable_s is not None and 0.0 < cut.perceivable_s - cut.onset_s < 1.0
        assert math.isfinite(cut.perceived_ttc_s)
    finally:
        sim.destroy()


def test_a_verdict_of_the_older_careful_driver_is_made_again_when_a_campaign_is_summarised():
    """Rows written with the headway-gated reference are re-judged from their steps: the blind ego 60 m behind
    a lead braking at 6 m/s^2 was 'unavoidable' (that reference hit the lead too); today's stops 38 m short."""
    from genesis_rl.campaigns.summary import rejudge_careful_driver

    records = _blind_ego_behind_a_braking_lead(60.0)
    braking = ActorEvent("lead_braking", 5, 1.0, 1.0)
    old = {"mode": "non_detection", "blame": "unavoidable", "evidence": {"stoppable": True}, "oracle_collides": None,
           "reference": "UN R157 careful driver",
           "careful_driver": {"reference": "UN R157 careful driver", "collides": True, "min_gap_m": -0.2}}
    again = rejudge_careful_driver(old, [braking.as_dict()], records)
    assert again["blame"] == "control" and again["reference"] == R157.name
    assert again["careful_driver"]["collides"] is False and again["careful_driver"]["min_gap_m"] > 30.0
    assert again["mode"] == "non_detection" and old["blame"] == "unavoidable"  # the row's other labels stay
    # today's verdicts, and blames without a careful driver, are left as the campaign made them
    assert rejudge_careful_driver(again, [braking.as_dict()], records) is again
    plain = {"blame": "perception", "evidence": {}, "oracle_collides": False}
    assert rejudge_careful_driver(plain, [], records) is plain
