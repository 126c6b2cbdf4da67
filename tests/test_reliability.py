"""Nothing lost, nothing mixed (issue 21): --force replaces only our own folders, one writer per output
folder, training resumes exactly, and sizes that would exhaust memory or run for days are refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from genesis_rl.cli import main

TINY_RUN = """
[env]
map = "urban"
scenes = 3
system = "blind"
episode_steps = 10          # episodes cross rollout boundaries: a checkpoint falls mid-episode
camera_width = 64
camera_height = 48
obs_width = 36
obs_height = 36

[ppo]
n_steps = 16
batch_size = 8
n_epochs = 2

[train]
total_timesteps = 64
checkpoint_every = 16
seed = 3
torch_threads = 1
"""


def _weights(path: Path) -> dict:
    from stable_baselines3 import PPO

    model = PPO.load(path, device="cpu")
    return {**{f"policy.{k}": v for k, v in model.policy.state_dict().items()},
            **{f"optimizer.{k}": v for k, v in _flat(model.policy.optimizer.state_dict()).items()}}


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        elif isinstance(v, list):
            out.update(_flat(dict(enumerate(v)), f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


@pytest.mark.render
def test_an_interrupted_and_resumed_run_matches_an_uninterrupted_one(tmp_path, monkeypatch, capsys) -> None:
    import torch

    from genesis_rl.env.genesis_env import GenesisEnv

    config = tmp_path / "tiny.toml"
    config.write_text(TINY_RUN)
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main(["train", "--config", str(config), "--out", str(whole), "--quiet"]) == 0

    step = GenesisEnv.step
    calls = {"n": 0}

    def interrupted_step(self, action):  # noqa: ANN001, ANN202 - stopped 12 steps after the checkpoint at 32
        calls["n"] += 1
        if calls["n"] == 45:
            raise KeyboardInterrupt
        return step(self, action)

    monkeypatch.setattr(GenesisEnv, "step", interrupted_step)
    assert main(["train", "--config", str(config), "--out", str(cut), "--quiet"]) == 130
    monkeypatch.setattr(GenesisEnv, "step", step)
    assert "--resume continues from the checkpoint at step 32" in capsys.readouterr().err
    assert json.loads((cut / "checkpoints" / "last.json").read_text())["timesteps"] == 32
    rows_at_cut = (cut / "episodes.csv").read_text().splitlines()
    assert len(rows_at_cut) == 1 + 4  # episodes ended at 10, 20, 30, and at 40, after the checkpoint
    assert main(["train", "--out", str(cut), "--resume", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["timesteps"] == 64 and result["trained_steps_now"] == 32

    # the same episodes, once each, with the same numbers
    assert (cut / "episodes.csv").read_text() == (whole / "episodes.csv").read_text()
    assert len((whole / "episodes.csv").read_text().splitlines()) == 1 + 6
    # the same weights and optimizer state, bit for bit (CPU, one torch thread)
    a, b = _weights(whole / "agent.zip"), _weights(cut / "agent.zip")
    assert a.keys() == b.keys() and len(a) > 10
    different = [k for k in a if isinstance(a[k], torch.Tensor) and not torch.equal(a[k], b[k])
                 or not isinstance(a[k], torch.Tensor) and a[k] != b[k]]
    assert different == []
    # a checkpoint holds the policy after its update: step_32 is not the initial policy
    assert _weights(cut / "checkpoints" / "step_00000032.zip")["optimizer.state.0.step"] > 0
