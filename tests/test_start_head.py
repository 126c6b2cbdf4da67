"""``env.start_head`` (issue 33): an agent's first action chooses where the held knobs start (the sun's altitude,
and its bearing from the ego's heading), as the searches choose their start; that step is not simulated, the
episode then runs its full length from the chosen start, and campaigns let a trained agent choose only where
policies choose (``start = "natural"``)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from builders import tiny_run

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.zoo.members import ODD_DIR, env_settings, zoo_member


def _action(env, **by_knob: float) -> np.ndarray:
    a = np.zeros(env.action_space.shape, np.float32)
    for name, value in by_knob.items():
        a[list(env.mapper.knobs).index(name)] = value
    return a


def test_a_start_head_is_refused_where_it_cannot_work():
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

    with pytest.raises(UserInputError, match="env.start_head = true needs a features observation .* not 'image'"):
        EnvConfig(start_head=True)
    with pytest.raises(UserInputError, match="env.start_head = true, but no knob .* is held"):
        GenesisEnv(system="blind", scenes=2, observation="features", start_head=True)  # paper dynamics: none held
    env = GenesisEnv(system="blind", scenes=2, observation="features", dynamics="natural", episode_steps=8)
    try:
        with pytest.raises(UserInputError, match="reset option start_head = true needs env.start_head = true"):
            env.reset(options={"scene": 0, "episode_seed": 1, "start_head": True})
    finally:
        env.close()


@pytest.mark.render
def test_the_start_step_sets_the_sun_from_the_action_and_the_episode_runs_in_full_from_there():
    from genesis_rl.env.genesis_env import GenesisEnv
    from genesis_rl.env.observation import feature_size

    member = zoo_member("glare_blind")  # urban_any_hour: every altitude allowed, glare too
    env = GenesisEnv(**{**env_settings(member), "scenes": 3, "episode_steps": 6, "observation": "features",
                        "start_head": True})
    try:
        assert {"sun_altitude_angle", "sun_azimuth_angle"} <= set(env.held_knobs)
        assert env.observation_space.shape == (4 * feature_size(len(env.mapper.knobs)) + 1,)  # the flag: last
        obs, _ = env.reset(options={"scene": 1, "episode_seed": 3})
        assert obs[-1] == 1.0 and env.choosing_start
        heading = env._loop.heading_deg
        obs, reward, terminated, truncated, info = env.step(_action(env, sun_altitude_angle=-70 / 165,
                                                                     sun_azimuth_angle=0.0))
        assert obs[-1] == 0.0 and reward == 0.0 and not (terminated or truncated) and env.records == []
        assert info["start_step"] and info["start"]["sun_altitude_angle"] == pytest.approx(5.0, abs=1e-4)
        assert info["start"]["sun_azimuth_angle"] == pytest.approx(heading % 360, abs=1e-4)  # straight ahead
        assert info["start"]["sun_bearing"] == pytest.approx(0.0, abs=1e-4)  # training logs it (episodes.csv)
        assert env.episode_start["sun_altitude_angle"] == pytest.approx(5.0, abs=1e-4)
        steps = 0
        while True:
            *_, terminated, truncated, _ = env.step(_action(env))
            steps += 1
            if terminated or truncated:
                break
        assert steps == 6 and len(env.records) == 6  # the start step is not one of the episode's steps
        assert env.records[0].conditions.sun_glare  # the sun 5 deg up, ahead
        # 0 keeps the episode's start (an untrained head starts where every episode would); -1 and +1 reach the
        # knob's ends; the azimuth's +-1 puts the sun behind the ego
        for a_alt, a_az, alt, bearing in ((0.0, 1.0, 75.0, 180.0), (-1.0, -0.5, -90.0, -90.0), (1.0, 0.25, 90.0, 45.0)):
            env.reset(options={"scene": 1, "episode_seed": 3})
            env.step(_action(env, sun_altitude_angle=a_alt, sun_azimuth_angle=a_az))
            assert env.weather["sun_altitude_angle"] == pytest.approx(alt, abs=1e-4)
            off = (env.weather["sun_azimuth_angle"] - heading + 180.0) % 360.0 - 180.0
            assert abs((off - bearing + 180.0) % 360.0 - 180.0) < 1e-4
        obs, _ = env.reset(options={"scene": 1, "episode_seed": 3, "start_head": False})
        assert obs[-1] == 0.0 and not env.choosing_start  # this episode plays from the start weather
        env.step(_action(env, sun_altitude_angle=-1.0))
        assert len(env.records) == 1 and env.records[0].knobs["sun_altitude_angle"] == pytest.approx(75.0, abs=0.01)
    finally:
        env.close()
    day = GenesisEnv(**{**env_settings(zoo_member("low_sun")), "scenes": 3, "episode_steps": 6,
                        "observation": "features", "start_head": True})
    try:  # urban_day: a night start is moved back inside, onto the horizon
        day.reset(options={"scene": 1, "episode_seed": 3})
        day.step(_action(day, sun_altitude_angle=-1.0, sun_azimuth_angle=1.0))
        assert 0.0 <= day.weather["sun_altitude_angle"] < 1.0
    finally:
        day.close()


def test_an_absolute_start_action_names_one_altitude_whatever_the_draw_and_the_count_bonus_pays_once():
    """env.start_action = "absolute": -1..+1 spans the knob's range, so one action is one sun altitude on every
    episode (relative: 0 keeps the episode's start); env.start_bonus pays start_bonus / sqrt(n) at the
    first tick, n the starts chosen in the action's cell, and nothing after."""
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

    with pytest.raises(UserInputError, match="env.start_action = 'corner'; allowed: relative, absolute"):
        EnvConfig(start_action="corner")
    with pytest.raises(UserInputError, match="env.start_bonus needs env.start_head = true"):
        EnvConfig(start_bonus=10.0)
    with pytest.raises(UserInputError, match=r"env.start_bonus_cells = 1 must be in 2..64 cells \(an integer\)"):
        EnvConfig(start_bonus_cells=1)
    with pytest.raises(UserInputError, match=r"env.start_bonus = -1.0 must be in 0..1e\+06 \(a finite number"):
        EnvConfig(start_bonus=-1.0)
    settings = {**env_settings(zoo_member("glare_blind")), "system": "blind", "system_kwargs": {}, "scenes": 3,
                "episode_steps": 3, "observation": "features", "start_head": True, "start_spread": 1.0,
                "camera_width": 64, "camera_height": 48}
    sun = ("sun_altitude_angle", "sun_azimuth_angle")
    with pytest.raises(UserInputError, match="env.start_bonus_knobs: \\['fog_density'\\] are not held"):
        GenesisEnv(**{**settings, "episode_steps": 256, "start_bonus": 1.0, "start_bonus_knobs": ("fog_density",)})
    with pytest.raises(UserInputError, match="env.start_bonus_knobs: \\['lead_decel'\\] are not among env.knobs"):
        EnvConfig(start_bonus_knobs=("lead_decel",))
    env = GenesisEnv(**{**settings, "start_action": "absolute", "start_bonus": 40.0, "start_bonus_cells": 4,
                        "start_bonus_knobs": sun})
    plain = GenesisEnv(**{**settings, "start_action": "absolute"})
    try:
        drawn, ticks = [], []
        for seed, a_alt, cell_n in ((3, 0.1, 1), (4, 0.1, 2), (5, -0.9, 1), (6, 0.2, 3)):
            rewards = []
            for e in (env, plain):
                e.reset(options={"scene": 1, "episode_seed": seed})
                drawn.append(e.episode_start["sun_altitude_angle"])
                e.step(_action(e, sun_altitude_angle=a_alt, sun_azimuth_angle=0.0))
                assert e.weather["sun_altitude_angle"] == pytest.approx(90.0 * a_alt, abs=1e-4)  # -90 + (a+1)/2 180
                rewards.append([e.step(_action(e))[1] for _ in range(3)])
            ticks.append(rewards)
            bonus = [a - b for a, b in zip(*rewards, strict=True)]
            assert bonus == pytest.approx([40.0 / cell_n ** 0.5, 0.0, 0.0], abs=1e-9)
        assert drawn == pytest.approx([75.0] * 8, abs=0.01)  # a relative action of 0.1 would give 76.5 deg
        assert env.start_counts == {(2, 2): 3, (0, 2): 1}
    finally:
        env.close()
        plain.close()


#: SAC with a start head for a few dozen steps on the oracle inside highway_day (oracle_highway's system and ODD),
#: trained on urban scenes as the zoo's agents are: the plumbing is under test
def tiny_head_agent(odd: Path) -> str:
    return tiny_run(env={"system": "oracle", "odd": str(odd), "dynamics": "natural", "observation": "features",
                         "start_head": True, "obs_width": None, "obs_height": None},
                    ppo={"n_steps": None, "batch_size": None, "n_epochs": None},
                    train={"algorithm": "sac", "total_timesteps": 32, "envs": 1, "seed": 1},
                    sac={"learning_starts": 8, "batch_size": 8, "buffer_size": 1000, "net_arch": [8]})


@pytest.mark.render
def test_a_trained_head_chooses_its_start_in_natural_campaigns_only(tmp_path, capsys):
    """Training logs each episode's chosen start and resumes across episodes that began with a start step; in a
    campaign the agent's first deterministic action is its start where policies choose, and not otherwise."""
    from genesis_rl.adversaries.agent import load_agent
    from genesis_rl.campaigns.campaign import run_campaign
    from genesis_rl.campaigns.campaign_spec import CampaignSpec, env_settings_for
    from genesis_rl.campaigns.records import load_record
    from genesis_rl.world.knobs import Weather

    run = tmp_path / "head"
    config = tmp_path / "head.toml"
    config.write_text(tiny_head_agent(ODD_DIR / "highway_day.toml"))
    assert main(["train", "--config", str(config), "--out", str(run), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume", "--steps", "48", "--quiet"]) == 0  # mid-episode
    assert json.loads(capsys.readouterr().out)["timesteps"] == 48
    rows = list(csv.DictReader((run / "episodes.csv").open()))
    assert len(rows) == 4  # 48 steps / (10 + the start step)
    assert all(0.0 <= float(r["start_sun_altitude_angle"]) <= 90.0 for r in rows)
    starts: dict[str, float] = {}
    for start in ("natural", "fixed"):
        spec = CampaignSpec(policies=("agent",), map="urban", scenes=1, seed=2, steps=8, agent=str(run),
                            env=env_settings_for(str(run), None, None), options={"start": start}, records="all")
        run_campaign(spec, tmp_path / start, progress=False)
        rec = load_record(next((tmp_path / start / "records").glob("agent_*.json")))
        assert len(rec["schedule"]) == 8  # the campaign's steps, after the start step
        starts[start] = rec["start_weather"]["sun_altitude_angle"]
        if start == "natural":  # the start the agent's first action names, from the scene's first observation
            from genesis_rl.core.config import from_mapping
            from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

            env = GenesisEnv(from_mapping(EnvConfig, {**spec.env, "catalog": str(tmp_path / start / "catalog.json"),
                                                      "episode_steps": 8}, "env"))
            try:
                obs, _ = env.reset(options={"scene": rec["scene"]["index"], "episode_seed": rec["episode_seed"]})
                action, _ = load_agent(run).predict(obs, deterministic=True)
                want = env.chosen_start(action)
            finally:
                env.close()
            got = Weather.from_recorded(rec["start_weather"])
            assert got["sun_altitude_angle"] == pytest.approx(want["sun_altitude_angle"], abs=1e-3)
            assert got["sun_azimuth_angle"] == pytest.approx(want["sun_azimuth_angle"], abs=1e-3)
    assert starts["fixed"] == 75.0  # the start weather: a fixed campaign gives no policy a choice
    from genesis_rl.benchmark.matrix import agent_env

    played = agent_env("oracle_highway", str(run))  # the benchmark plays it with its head, on the member's map
    assert played["start_head"] is True and played["map"] == "highway" and played["system"] == "oracle"


def test_evaluate_warns_when_a_start_head_agent_plays_a_fixed_start(tmp_path, capsys):
    """An agent trained with env.start_head plays from the start weather under --start fixed (the default): the
    command says so, and names --start natural; under --start natural it says nothing."""
    run = tmp_path / "head"
    config = tmp_path / "head.toml"
    config.write_text(tiny_head_agent(ODD_DIR / "highway_day.toml"))
    assert main(["train", "--config", str(config), "--out", str(run), "--quiet"]) == 0
    for start, warned in (("fixed", True), ("natural", False)):
        capsys.readouterr()
        assert main(["evaluate", "--agent", str(run), "--policies", "agent", "--map", "urban", "--scenes", "1",
                     "--steps", "4", "--start", start, "--out", str(tmp_path / start), "--no-report",
                     "--quiet"]) == 0
        assert ("pass --start natural" in capsys.readouterr().err) is warned
