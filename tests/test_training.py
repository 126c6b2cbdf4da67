"""Training: config validation, the run folder, checkpoints and resume with the step count intact."""

from __future__ import annotations

import json

import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.training.config import RunConfig, load_run_config


def test_paper_config_holds_the_papers_values() -> None:
    cfg = load_run_config("configs/paper.toml")
    assert cfg == RunConfig()  # the file spells out the defaults
    assert (cfg.ppo.n_steps, cfg.train.total_timesteps, cfg.env.episode_steps) == (2048, 40960, 512)
    assert (cfg.env.reward.collision_weight, cfg.env.reward.proximity_weight) == (500.0, 100.0)
    assert cfg.env.max_step_fraction == 0.05 and cfg.env.scenes == 1202


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ("[ppo]\nlearning_rat = 0.1\n", "unknown key\\(s\\) ppo.learning_rat; allowed in \\[ppo\\]: learning_rate"),
        ("[train]\nenvs = 'two'\n", "train.envs = 'two' must be an integer"),
        ("[train]\nenvs = 0\n", "train.envs = 0 must be in 1..64"),
        ("[env]\nknobs = ['fog']\n", "unknown knob 'fog'"),
        ("[env.reward]\ncollision_weight = -1\n", "reward.collision_weight = -1.0 must be a finite number >= 0"),
        ("[trainer]\n", "unknown table\\(s\\) \\['trainer'\\]"),
    ],
)
def test_bad_config_names_the_key(tmp_path, toml: str, message: str) -> None:
    p = tmp_path / "c.toml"
    p.write_text(toml)
    with pytest.raises(UserInputError, match=message):
        load_run_config(p)


def test_train_refuses_an_existing_run_folder(tmp_path, capsys) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "something").write_text("x")
    assert main(["train", "--out", str(run), "--system", "blind", "--scenes", "2"]) == 2
    assert "exists; pass --resume to continue it or --force" in capsys.readouterr().err


@pytest.mark.render
def test_train_checkpoints_and_resumes_with_the_step_count(tmp_path, capsys) -> None:
    run = tmp_path / "run"
    common = ["--quiet"]
    assert main(["train", "--out", str(run), "--system", "oracle", "--scenes", "3", "--steps", "32",
                 "--n-steps", "16", "--episode-steps", "8", *common]) == 0
    assert "scenes urban" not in capsys.readouterr().err  # --quiet silences the catalog's bar as well
    first = json.loads((run / "checkpoints" / "last.json").read_text())
    assert first["timesteps"] == 32
    for name in ("agent.zip", "config.toml", "run.json", "catalog.json", "episodes.csv"):
        assert (run / name).is_file(), name
    assert any((run / "tb").glob("events.out.tfevents.*"))
    episodes = (run / "episodes.csv").read_text().strip().splitlines()
    assert len(episodes) == 1 + 4  # header + 32 steps / 8 per episode
    assert "violation_collision" in episodes[0] and "mean_fog_density" in episodes[0]
    from stable_baselines3 import PPO

    from genesis_rl.env import GenesisEnv

    agent = PPO.load(run / "agent.zip", device="cpu")
    env = GenesisEnv(system="oracle", scenes=2, episode_steps=4)
    try:
        obs, _ = env.reset(seed=0)
        action, _ = agent.predict(obs, deterministic=True)
        assert action.shape == (5,) and env.action_space.contains(action.astype("float32"))
    finally:
        env.close()
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume", "--steps", "48", *common]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["timesteps"] == 48 and result["trained_steps_now"] == 16
    assert json.loads((run / "checkpoints" / "last.json").read_text())["timesteps"] == 48
    checkpoint = run / "checkpoints" / "step_00000048.zip"  # the one last.json names
    good = checkpoint.read_bytes()
    checkpoint.write_bytes(b"not a zip")
    assert main(["train", "--out", str(run), "--resume", "--steps", "64", *common]) == 2
    assert "cannot be loaded" in capsys.readouterr().err
    checkpoint.write_bytes(good)
    last = run / "checkpoints" / "last.json"
    meta = json.loads(last.read_text())
    for steps, message in ((-16, "timesteps = -16; allowed: 0..48"), (64, "timesteps = 64; allowed: 0..48"),
                           (32, "it names 'step_00000048.zip'")):
        last.write_text(json.dumps({**meta, "timesteps": steps}))
        assert main(["train", "--out", str(run), "--resume", *common]) == 2
        assert message in capsys.readouterr().err
    last.write_text(json.dumps(meta))
    assert main(["train", "--out", str(run), "--resume", "--steps", "32", *common]) == 2
    assert "has trained 48 steps already; allowed: --steps >= 48" in capsys.readouterr().err
    last.write_text("{")
    assert main(["train", "--out", str(run), "--resume", "--steps", "64", *common]) == 2
    assert "last.json' is damaged (expected JSON with an integer 'timesteps')" in capsys.readouterr().err
    last.write_text(json.dumps(meta))
    checkpoint.unlink()
    assert main(["train", "--out", str(run), "--resume", "--steps", "64", *common]) == 2
    assert "step_00000048.zip missing); start it again with --force" in capsys.readouterr().err


@pytest.mark.parametrize(("table", "key"), [("train", "seed"), ("env", "catalog_seed")])
def test_a_negative_seed_in_a_config_is_named(tmp_path, table, key) -> None:
    path = tmp_path / "c.toml"
    path.write_text(f"[{table}]\n{key} = -1\n")
    with pytest.raises(UserInputError, match=rf"{table}\.{key} = -1; allowed: an integer"):
        load_run_config(path)
    assert getattr(getattr(load_run_config(path, {table: {key: 3}}), table), key) == 3


@pytest.mark.parametrize(("text", "message"), [
    ("env = 3\n", "[env] must be a table, got 3"),
    ("[env]\nreward = 5\n", "[env.reward] must be a table, got 5"),
    ("[env]\ncamera_width = 0\n", "env.camera_width = 0 must be in 16..4096"),
    ("[env]\ndisabled_knobs = ['fog_density', 'precipitation', 'precipitation_deposits', 'sun_altitude_angle', "
     "'sun_azimuth_angle']\n", "disable every knob the agent turns"),
    ("[ppo]\nn_epochs = 0\n", "ppo.n_epochs = 0 must be >= 1"),
    ("[ppo]\ndevice = 'tpu'\n", "ppo.device = 'tpu'; allowed: auto, cpu, cuda, cuda:N, mps"),
    ("[ppo]\nclip_range = -0.2\n", "ppo.clip_range = -0.2 must be > 0"),
    ("[train]\nseed = 99999999999\n", "train.seed = 99999999999; allowed: an integer in 0..4294967295"),
    ("[train]\ntorch_threads = -1\n", "train.torch_threads = -1 must be >= 0"),
])
def test_bad_config_values_are_named(tmp_path, text, message) -> None:
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(UserInputError) as err:
        load_run_config(path)
    assert message in str(err.value)


def test_a_non_utf8_config_and_a_failed_start_leave_nothing_behind(tmp_path, capsys) -> None:
    path = tmp_path / "c.toml"
    path.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(UserInputError, match="is not UTF-8 text"):
        load_run_config(path)
    run = tmp_path / "run"
    assert main(["train", "--out", str(run), "--system", "nosuch", "--scenes", "2", "--steps", "16",
                 "--n-steps", "16", "--episode-steps", "8", "--quiet"]) == 2
    assert "env.system: system 'nosuch' is not an import path" in capsys.readouterr().err
    assert not run.exists()  # so the corrected command runs without --force
    a_file = tmp_path / "afile"
    a_file.write_text("x")
    assert main(["train", "--out", str(a_file), "--system", "blind", "--scenes", "2", "--quiet"]) == 2
    assert f"'{a_file}' is a file; expected a folder" in capsys.readouterr().err


def test_sacs_updates_take_one_thread_unless_the_config_names_more() -> None:
    """Two SAC trainings side by side ran 4.4x slower with torch's default two update threads (docs/benchmarks.md):
    SAC's updates default to one thread, PPO's image minibatches to torch's default, an explicit setting wins."""
    from dataclasses import replace

    from genesis_rl.training.train import update_threads

    cfg = load_run_config(None)
    assert cfg.train.algorithm == "ppo" and update_threads(cfg) == 0
    sac = replace(cfg, train=replace(cfg.train, algorithm="sac"))
    assert update_threads(sac) == 1
    assert update_threads(replace(sac, train=replace(sac.train, torch_threads=2))) == 2
