"""The lead's braking as a knob of the env (issue 32): it acts on lite's traffic as declared, the ODD's traffic
conditions hold it, a tester's measurements of the actor are observed, and campaigns record and replay it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.env.observation import ACTOR_FEATURES, FEATURES, GAP_SCALE, SPEED_SCALE, feature_size

HIGHWAY = dict(map="highway", scenes=8)


def _env(tmp_path: Path | None = None, **kw) -> GenesisEnv:
    cfg = dict(HIGHWAY, knobs=("fog_density", "lead_decel"), dynamics="natural", observation="features",
               episode_steps=200)
    cfg.update(kw)
    return GenesisEnv(EnvConfig(**cfg))


def test_lead_decel_brakes_the_lead_at_the_demanded_deceleration_and_releases_it():
    env = _env()
    try:
        env.reset(seed=0, options={"scene": 3, "episode_seed": 11})
        traffic = env._sim.traffic  # type: ignore[union-attr]
        assert traffic.braking_vehicle == -1
        lead_id = env._sim.lead().vehicle_id  # type: ignore[union-attr]
        checked = 0
        for k in range(60):
            v_before = float(traffic.v[lead_id])
            _, _, _, _, info = env.step(np.array([0.0, 1.0], np.float32))
            decel = info["knobs"]["lead_decel"]
            # natural rate 4 m/s^2 per s: 0.2 per 0.05 s step, from 0
            assert decel == pytest.approx(min(8.0, 0.2 * (k + 1)), abs=1e-9)
            assert traffic.braking_vehicle == lead_id
            v_after = float(traffic.v[lead_id])
            if v_after > 0.0:
                assert (v_before - v_after) / env.dt == pytest.approx(decel, abs=1e-9)
                checked += 1
        assert checked >= 20
        for _ in range(40):  # the knob back to 0: the lead is the autopilot's again
            _, _, _, _, info = env.step(np.array([0.0, -1.0], np.float32))
        assert info["knobs"]["lead_decel"] == 0.0 and traffic.braking_vehicle == -1
    finally:
        env.close()


def odd_with_traffic(tmp_path: Path, **traffic: float) -> str:
    """highway_day with a ``[traffic]`` table of ``traffic``'s bounds, written under ``tmp_path``."""
    src = Path(__file__).resolve().parents[1] / "configs" / "odd" / "highway_day.toml"
    path = tmp_path / "odd.toml"
    path.write_text(src.read_text() + "\n[traffic]\n" + "".join(f"{k} = {v}\n" for k, v in traffic.items()))
    return str(path)


def test_the_odd_holds_lead_braking_at_its_traffic_bound_and_labels_beyond_it(tmp_path):
    odd = odd_with_traffic(tmp_path, max_lead_decel=3.0)
    for keep_inside in (True, False):
        env = _env(odd=odd, odd_keep_inside=keep_inside)
        try:
            env.reset(seed=0, options={"scene": 3, "episode_seed": 11})
            for _ in range(40):
                env.step(np.array([0.0, 1.0], np.float32))
            decels = [r.knobs["lead_decel"] for r in env.records]
            status = [r.odd_status for r in env.records]
        finally:
            env.close()
        if keep_inside:
            assert max(decels) == pytest.approx(3.0, abs=0.01) and max(decels) <= 3.0
            assert "outside" not in status
        else:
            assert max(decels) == pytest.approx(8.0) and status[-1] == "outside"
            assert all((s == "outside") == (d > 3.0) for d, s in zip(decels, status, strict=True))


def test_a_start_weather_braking_harder_than_the_odd_allows_is_refused(tmp_path):
    with pytest.raises(UserInputError, match=r"lead_decel 7 m/s\^2 > 3"):
        EnvConfig(**HIGHWAY, knobs=("lead_decel",), odd=odd_with_traffic(tmp_path, max_lead_decel=3.0),
                  start_weather="clear_noon,lead_decel=7")


def test_features_add_what_a_tester_measures_of_the_actor():
    env = _env()
    try:
        obs, _ = env.reset(seed=0, options={"scene": 3, "episode_seed": 11})
        n = feature_size(2, actors=True)
        assert n == 2 + len(FEATURES) + len(ACTOR_FEATURES) and obs.shape == (env.config.obs_history * n,)
        for _ in range(30):
            obs, *_ = env.step(np.array([0.0, 1.0], np.float32))
        lead = env._sim.lead()  # type: ignore[union-attr]
        ego_speed = env._loop.ego.speed  # type: ignore[union-attr]
        row = obs[-n:]
        assert row[-2] == pytest.approx(min(lead.gap / GAP_SCALE, 1.0), abs=1e-6)
        assert row[-1] == pytest.approx(0.5 + 0.5 * (ego_speed - lead.speed) / SPEED_SCALE, abs=1e-6)
        assert row[-1] > 0.5  # the braking lead is being closed on
    finally:
        env.close()
    weather_only = GenesisEnv(EnvConfig(**HIGHWAY, knobs=("fog_density",), observation="features"))
    try:  # weather-only agents keep their observation
        assert weather_only.observation_space.shape == (weather_only.config.obs_history * feature_size(1),)
    finally:
        weather_only.close()


def test_a_backend_that_does_not_realise_an_actor_knob_is_refused_naming_the_setting(tmp_path, monkeypatch):
    from genesis_rl.sim.carla.backend import CarlaBackend

    monkeypatch.setattr(CarlaBackend, "actor_knobs", ())
    with pytest.raises(UserInputError, match=r"env.knobs: actor knob\(s\) \['lead_decel'\] are not realised by "
                                             r"env.backend = 'carla'; it realises: none"):
        EnvConfig(knobs=("fog_density", "lead_decel"), backend="carla", catalog=None)


def test_on_carla_the_lead_leaves_the_traffic_manager_brakes_by_target_velocity_and_rejoins():
    """``lead_decel`` on a CARLA server, offline with the client's real command types."""
    carla = pytest.importorskip("carla")
    from genesis_rl.sim.carla.actor_control import LeadBraking
    from genesis_rl.sim.interface import LeadInfo

    braking = LeadBraking()
    ids = {0: 100, 4: 104, 7: 107}
    asked: list[int] = []

    def lead():
        asked.append(1)
        return LeadInfo(4, 20.0, 10.0)

    velocity = {4: (6.0, 8.0, 0.0)}  # 10 m/s
    cmds = braking.commands(carla, 8003, 0.0, 0.05, lead, ids.get, velocity.get)
    assert cmds == [] and not asked  # no braking: nothing asked of the server
    cmds = braking.commands(carla, 8003, 6.0, 0.05, lead, ids.get, velocity.get)
    assert [type(c).__name__ for c in cmds] == ["SetAutopilot", "ApplyTargetVelocity"]
    assert (cmds[0].actor_id, cmds[0].enabled, cmds[0].tm_port) == (104, False, 8003)
    v = cmds[1].velocity  # 10 m/s - 6 m/s^2 * 0.05 s = 9.7 m/s, along (0.6, 0.8)
    assert (cmds[1].actor_id, v.x, v.y, v.z) == (104, pytest.approx(5.82), pytest.approx(7.76), 0.0)
    velocity[4] = (0.03, 0.04, 0.0)  # 0.05 m/s: the next step stops it, never reverses it
    cmds = braking.commands(carla, 8003, 8.0, 0.05, lead, ids.get, velocity.get)
    assert [type(c).__name__ for c in cmds] == ["ApplyTargetVelocity"] and len(asked) == 1  # the same vehicle
    assert (cmds[0].velocity.x, cmds[0].velocity.y) == (0.0, 0.0)
    cmds = braking.commands(carla, 8003, 0.0, 0.05, lead, ids.get, velocity.get)
    assert [(type(c).__name__, c.actor_id, c.enabled) for c in cmds] == [("SetAutopilot", 104, True)]
    assert braking.vehicle == -1
    assert braking.commands(carla, 8003, 3.0, 0.05, lambda: None, ids.get, velocity.get) == []  # nobody ahead


@pytest.mark.render
def test_a_campaign_turning_the_lead_records_it_and_replays_it(tmp_path):
    from genesis_rl.campaigns.campaign import run_campaign
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.campaigns.records import load_record, replay_record

    env = {"knobs": ["fog_density", "lead_decel"], "dynamics": "natural"}
    spec = CampaignSpec(policies=("constant",), map="highway", scenes=1, seed=0, steps=80, env=env,
                        options={"constant_action": [0.0, 1.0]}, records="all")
    run_campaign(spec, tmp_path / "camp", workers=1, progress=False)
    record = load_record(next((tmp_path / "camp" / "records").glob("*.json")))
    col = record["knobs"].index("lead_decel")  # a record keeps every knob, the actor's among them
    assert [row[col] for row in record["schedule"][:3]] == pytest.approx([0.2, 0.4, 0.6], abs=1e-9)
    assert record["schedule"][-1][col] == pytest.approx(8.0)
    replay = replay_record(record, keep_frames=False)
    assert [r.knobs["lead_decel"] for r in replay["records"]][-1] == pytest.approx(8.0)
    assert replay["reproduced"]


def test_a_collision_with_a_lead_the_tester_braked_is_its_own_kind_of_failure():
    """Distinct-failure clustering keeps the actor event: the hit is 'lead braked by the tester'."""
    from genesis_rl.labels.distinct import what_was_hit

    env = _env(system="blind", episode_steps=400)
    try:
        env.reset(seed=0, options={"scene": 3, "episode_seed": 11})
        for _ in range(400):
            *_, info = env.step(np.array([0.0, 1.0], np.float32))
            if info["collision"]:
                break
        hit_at = len(env.records) - 1
        assert env.records[hit_at].collision.collided
        assert what_was_hit(env.records, hit_at, env.dt) == "lead braked by the tester"
    finally:
        env.close()


def test_a_carla_tick_sends_the_lead_brake_batch_before_it_ticks():
    pytest.importorskip("carla")
    from types import SimpleNamespace

    from genesis_rl.sim.carla.actor_control import CutIn, LeadBraking, TrafficBehaviour
    from genesis_rl.sim.carla.backend import CarlaSimulation
    from genesis_rl.sim.interface import LeadInfo, VehicleControl
    from genesis_rl.world.knobs import Weather

    calls: list[str] = []
    batches: list[list] = []
    vel = SimpleNamespace(x=10.0, y=0.0, z=0.0)
    snapshot = SimpleNamespace(find=lambda aid: SimpleNamespace(get_velocity=lambda: vel))

    def tick(timeout):
        calls.append("tick")
        return 7

    def apply_batch_sync(cmds, due_tick):
        calls.append("batch")
        batches.append(cmds)

    backend = SimpleNamespace(call=lambda what, fn, *a: fn(*a), timeout=1.0, tm_port=8000,
                              client=SimpleNamespace(apply_batch_sync=apply_batch_sync))
    sim = object.__new__(CarlaSimulation)
    sim._backend, sim._step = backend, 0
    sim._weather = Weather.default().replace(lead_decel=5.0)
    sim._applied_weather = sim._weather
    sim._control = sim._applied_control = VehicleControl()
    sim._actors = {0: SimpleNamespace(id=100), 3: SimpleNamespace(id=103)}
    sim._snapshot, sim._history, sim._queues, sim._images = snapshot, {}, {}, {}
    sim.world = SimpleNamespace(tick=tick, get_snapshot=lambda: snapshot)
    sim._lead_braking = LeadBraking()
    sim._cut_in, sim._traffic_behaviour, sim._braking_events = CutIn(), TrafficBehaviour(), []
    sim._tm = SimpleNamespace()  # at their defaults the cut-in and traffic knobs ask nothing of it
    sim.lead = lambda: LeadInfo(3, 15.0, 10.0)  # type: ignore[method-assign]
    sim._advance(1)
    assert calls == ["batch", "tick"]
    assert [(e.kind, e.vehicle_id, e.onset_s, e.perceivable_s) for e in sim.actor_events()] == [
        ("lead_braking", 3, 0.0, 0.0)]
    assert [(type(c).__name__, c.actor_id) for c in batches[0]] == [("SetAutopilot", 103), ("ApplyTargetVelocity", 103)]
    assert batches[0][1].velocity.x == pytest.approx(10.0 - 5.0 * sim.dt)



def test_a_slow_perception_pipeline_acts_on_detections_a_latency_late():
    """The timing member's system (issue 33): the controller gets each frame's detections 0.3 s (6 steps)
    late, and none at all from dropped frames; the fresh perception is the built-in system's."""
    from genesis_rl.sut.system.protocol import load_system

    env = _env(system="latency", system_kwargs={"latency_s": 0.3}, knobs=("lead_decel",))
    try:
        env.reset(seed=0, options={"scene": 3, "episode_seed": 11})
        system = env.system
        fresh: list[list] = []
        original = system.perceive

        def spy(frame):
            fresh.append(original(frame))
            return fresh[-1]

        system.perceive = spy  # type: ignore[method-assign]
        for _ in range(20):
            env.step(np.array([0.0], np.float32))
        delivered = [r.perception.n_detections for r in env.records]
        # reset perceived frame 0; the pipeline ran before the scene began, so until frame 0's own delivery
        # (6 steps later, at record 5) it delivers frame 0 in place of the earlier frames it had (not an
        # empty road); then record k brings the frame perceived at step k - 6 of the spied steps
        assert len(set(delivered[:6])) == 1 and delivered[0] > 0
        assert delivered[6:] == [len(f) for f in fresh[:14]]
    finally:
        env.close()
    dropping = load_system("latency", latency_s=0.0, drop_rate=1.0)
    assert dropping.identity()["drop_rate"] == 1.0
    with pytest.raises(UserInputError, match=r"latency_s"):
        load_system("latency", latency_s=-1.0)


def test_the_episode_likelihood_covers_the_lead_braking_with_its_declared_rate():
    """Weather and actors in one log-likelihood: a hand-checked two-knob step (odd/dynamics.py's random walk,
    sigma = the natural rate: fog 4 %/s, lead_decel 4 m/s^2/s)."""
    import math

    from genesis_rl.world.odd.dynamics import WeatherModel, natural_rate

    assert natural_rate("lead_decel") == 4.0
    model = WeatherModel(("fog_density", "lead_decel"))
    dt = 0.05
    before, after = {"fog_density": 10.0, "lead_decel": 0.0}, {"fog_density": 10.1, "lead_decel": 0.2}
    z_fog, z_lead = 0.1 / (4.0 * math.sqrt(dt)), 0.2 / (4.0 * math.sqrt(dt))
    by_hand = -0.5 * sum(math.log(2 * math.pi * 16.0 * dt) + z * z for z in (z_fog, z_lead))
    assert model.step_log_likelihood(before, after, dt) == pytest.approx(by_hand, rel=1e-12)
    assert model.surprise(before, after, dt) == pytest.approx(-0.5 * (z_fog**2 + z_lead**2), rel=1e-12)
    assert model.start_log_likelihood() == pytest.approx(-math.log(100.0) - math.log(8.0))
