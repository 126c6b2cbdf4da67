"""The agent's observation modes: both env checkers in every mode, the same seed gives the same observations,
and the features say what the system under test reported (env/observation.py)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.env.observation import FEATURES, OBSERVATIONS, feature_size, sb3_policy

STEPS = 6


def _env(mode: str, **kw):
    from genesis_rl.env import GenesisEnv

    return GenesisEnv(system="builtin", scenes=2, episode_steps=STEPS, observation=mode, **kw)


@pytest.mark.render
@pytest.mark.parametrize("mode", OBSERVATIONS)
def test_every_mode_passes_both_env_checkers(mode) -> None:
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = _env(mode)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            check_env(env, skip_render_check=True)
            sb3_check_env(env, warn=True)
    finally:
        env.close()


@pytest.mark.render
@pytest.mark.parametrize("mode", ["features", "image+features"])
def test_same_seed_same_observations(mode) -> None:
    def rollout():
        env = _env(mode)
        try:
            obs, _ = env.reset(seed=11)
            seen = [obs]
            for k in range(STEPS - 1):
                obs, *_ = env.step(np.full(5, 1.0 if k % 2 else -0.5, np.float32))
                seen.append(obs)
            return seen
        finally:
            env.close()

    a, b = rollout(), rollout()
    for x, y in zip(a, b, strict=True):
        if isinstance(x, dict):
            assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
        else:
            assert np.array_equal(x, y)


@pytest.mark.render
def test_features_are_what_the_system_reported_stacked_oldest_first() -> None:
    env = _env("features", obs_history=3)
    try:
        k, n = len(env.config.knobs), feature_size(len(env.config.knobs))
        obs, _ = env.reset(seed=2)
        assert obs.shape == (3 * n,) and obs.dtype == np.float32
        assert np.all(obs[: 2 * n] == 0.0)  # nothing before the first step
        first = obs[2 * n :]
        assert np.allclose(first[:k], env.weather.normalized(env.config.knobs))
        assert first[k + FEATURES.index("time")] == 0.0
        out = env._loop.output
        assert first[k + FEATURES.index("n_detections")] == pytest.approx(min(len(out.detections) / 10, 1.0))
        assert first[k + FEATURES.index("ego_speed")] == pytest.approx(env._loop.ego.speed / 30.0, abs=1e-6)
        obs2, *_ = env.step(np.ones(5, np.float32))
        assert np.array_equal(obs2[n : 2 * n], first)  # the history moved on by one step
        now = obs2[2 * n :]
        assert now[k + FEATURES.index("time")] == pytest.approx(0.05 / 25.6)  # seconds over the paper's episode
        assert np.allclose(now[:k], env.weather.normalized(env.config.knobs))
        rec = env.records[-1]
        assert now[k + FEATURES.index("throttle")] == pytest.approx(rec.ego.throttle)
        assert now[k + FEATURES.index("brake")] == pytest.approx(rec.ego.brake)
        follows = np.isfinite(rec.lead.perceived_distance)
        assert now[k + FEATURES.index("follows")] == float(follows)
        states = [f for f in FEATURES if f.startswith("state_")]
        assert sum(now[k + FEATURES.index(s)] for s in states) == (1.0 if rec.ego.status in
                                                                   [s[6:] for s in states] else 0.0)
    finally:
        env.close()


def test_observation_settings_are_checked() -> None:
    from genesis_rl.env.genesis_env import EnvConfig

    with pytest.raises(UserInputError, match="env.observation = 'pixels'; allowed: image, image\\+knobs, features"):
        EnvConfig(observation="pixels")
    with pytest.raises(UserInputError, match="obs_knobs = true and env.observation = 'features' disagree"):
        EnvConfig(obs_knobs=True, observation="features")
    with pytest.raises(UserInputError, match="env.obs_history = 0 must be in 1..16"):
        EnvConfig(obs_history=0)
    assert EnvConfig(obs_knobs=True).observation_mode == "image+knobs"
    assert [sb3_policy(m) for m in OBSERVATIONS] == ["CnnPolicy", "MultiInputPolicy", "MlpPolicy", "MultiInputPolicy"]


def test_shipped_reactive_configs_load_and_log_std_init_is_checked() -> None:
    from genesis_rl.training.config import PPOConfig, load_run_config

    for path in ("configs/reactive.toml", "configs/reactive_long.toml", "configs/reactive_night.toml",
                 "configs/reactive_sac.toml"):
        cfg = load_run_config(path, {"env": {"scenes": 2}})
        assert cfg.env.observation_mode == "features" and cfg.env.dynamics == "natural" and cfg.env.odd
    sac = load_run_config("configs/reactive_sac.toml", {"env": {"scenes": 2}})
    assert sac.train.algorithm == "sac" and sac.device == sac.sac.device and sac.sac.buffer_size >= 40960
    assert sac.sac.net_arch == (64, 64) and sac.env.start_spread == 1.0
    assert load_run_config("configs/reactive_long.toml", {"env": {"scenes": 2}}).ppo.log_std_init == -1.0
    with pytest.raises(UserInputError, match=r"ppo.log_std_init = -9.0 must be in -5..2"):
        PPOConfig(log_std_init=-9.0)
    from genesis_rl.training.config import SACConfig, TrainConfig

    for bad in ("autoo", "auto_", "-0.1", "fast"):
        with pytest.raises(UserInputError, match=rf"sac.ent_coef = '{bad}'; allowed: 'auto', 'auto_X' or 'X'"):
            SACConfig(ent_coef=bad)
    assert SACConfig(ent_coef="auto_0.1").sb3_ent_coef() == "auto_0.1"
    assert SACConfig(ent_coef="0.2").sb3_ent_coef() == 0.2
    with pytest.raises(UserInputError, match=r"sac.net_arch = \[64, 0\]: expected 1 or more layer widths"):
        SACConfig(net_arch=(64, 0))
    with pytest.raises(UserInputError, match="train.algorithm = 'a2c'; allowed: ppo, sac"):
        TrainConfig(algorithm="a2c")


def test_exploring_starts_spread_within_reach_stay_inside_the_odd_and_replay_from_the_episode_seed() -> None:
    """env.start_spread: each training episode starts at a random weather (drawn from its episode seed) that
    the knobs could reach in an episode, inside the ODD; campaigns drop the setting, so tests start at
    start_weather."""
    from genesis_rl.campaigns.campaign_spec import env_settings_for
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

    env = GenesisEnv(system="blind", scenes=2, episode_steps=512, odd="configs/odd/urban_all_day.toml",
                     dynamics="natural", start_spread=1.0, observation="features")
    try:
        starts = [env.exploring_start(s) for s in range(40)]
        fog = np.array([w["fog_density"] for w in starts])
        deposits = np.array([w["precipitation_deposits"] for w in starts])
        sun = np.array([w["sun_altitude_angle"] for w in starts])
        assert fog.max() > 40 and fog.min() < 10  # fog can reach its densest in an episode: spread widely
        assert deposits.max() <= 0.2 * 25.6 + 1e-9  # water builds at 0.2 %/s: at most 5.1 % in 25.6 s
        assert np.ptp(sun) <= 2 * 0.25 / 60 * 25.6 + 1e-9  # the sun moves 0.1 deg in an episode
        assert all(env.odd.contains(env.conditions_model.conditions(w)) for w in starts)
        assert min(env.conditions_model.conditions(w).visibility_m for w in starts) == pytest.approx(50, abs=1)
        assert env.exploring_start(7) == env.exploring_start(7) != env.exploring_start(8)
        env.reset(options={"scene": 0, "episode_seed": 7})
        assert env.weather == env.exploring_start(7)
    finally:
        env.close()
    with pytest.raises(UserInputError, match="env.start_spread = 1.5 must be in 0..1"):
        EnvConfig(start_spread=1.5)
    assert "start_spread" not in env_settings_for(None, "configs/reactive_sac.toml", None)
