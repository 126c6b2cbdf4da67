"""A recurrent agent (train.algorithm = "recurrent_ppo", sb3-contrib's RecurrentPPO): trained, checkpointed,
resumed to the bit with its envs' LSTM memory, loaded without unpickling and played with its memory."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from tests.builders import tiny_run

#: 10-step episodes and 16-step rollouts: every checkpoint falls inside an episode, so a resume that forgot the
#: envs' LSTM memory would take another path
TINY_RECURRENT = tiny_run(env={"observation": "features", "obs_history": 1, "obs_width": None, "obs_height": None},
                          train={"algorithm": "recurrent_ppo"}, recurrent={"lstm_hidden_size": 16})


def _state(path: Path) -> dict:
    from sb3_contrib import RecurrentPPO

    model = RecurrentPPO.load(path, device="cpu")
    flat = {f"policy.{k}": v for k, v in model.policy.state_dict().items()}
    opt = model.policy.optimizer.state_dict()["state"]
    flat.update({f"opt.{i}.{k}": v for i, s in opt.items() for k, v in s.items()})
    return flat


def _train(tmp_path: Path, name: str, *extra: str) -> Path:
    config = tmp_path / "recurrent.toml"
    config.write_text(TINY_RECURRENT)
    run = tmp_path / name
    assert main(["train", "--config", str(config), "--out", str(run), "--quiet", *extra]) == 0
    return run


def test_a_resumed_recurrent_run_matches_an_uninterrupted_one(tmp_path, capsys) -> None:
    import torch

    whole = _train(tmp_path, "whole")
    cut = _train(tmp_path, "cut", "--steps", "32")
    with np.load(cut / "checkpoints" / "step_00000032.sb3.npz") as z:
        memory = {k: z[k] for k in z.files if k.startswith("lstm/")}
    assert sorted(memory) == ["lstm/pi_c", "lstm/pi_h", "lstm/vf_c", "lstm/vf_h"]
    assert memory["lstm/pi_h"].shape == (1, 1, 16)
    assert np.abs(memory["lstm/pi_h"]).max() > 1e-3  # step 32 is 2 steps into an episode: a memory, not zeros
    assert main(["train", "--out", str(cut), "--resume", "--steps", "64", "--quiet"]) == 0
    capsys.readouterr()
    a, b = _state(whole / "agent.zip"), _state(cut / "agent.zip")
    assert "policy.lstm_actor.weight_hh_l0" in a and "policy.lstm_critic.weight_hh_l0" in a
    different = [k for k in a if not torch.equal(a[k], b[k])]
    assert different == []
    assert (cut / "episodes.csv").read_text() == (whole / "episodes.csv").read_text()
    assert "[recurrent]" in (whole / "config.toml").read_text()

    # the old way (--trust-pickle: SB3's own load) keeps no memory either; the checkpoint's is restored there too
    trusted = _train(tmp_path, "trusted", "--steps", "32")
    assert main(["train", "--out", str(trusted), "--resume", "--steps", "64", "--quiet", "--trust-pickle"]) == 0
    c = _state(trusted / "agent.zip")
    assert [k for k in a if not torch.equal(a[k], c[k])] == []

    # the memory is what the resume needs: a checkpoint whose LSTM states were lost is refused, naming them
    state = cut / "checkpoints" / "step_00000064.sb3.npz"
    with np.load(state) as z:
        kept = {k: z[k] for k in z.files if not k.startswith("lstm/")}
    with state.open("wb") as fh:
        np.savez(fh, **kept)
    assert main(["train", "--out", str(cut), "--resume", "--steps", "80", "--quiet"]) == 2
    assert "'lstm' is not the recurrent policy's four float32[1, 1, 16] states" in capsys.readouterr().err


def test_the_agent_plays_with_its_memory_and_starts_each_episode_without_one(tmp_path, capsys) -> None:
    run = _train(tmp_path, "run", "--steps", "16")
    from genesis_rl.adversaries import load_agent
    from genesis_rl.adversaries.agent import AgentPolicy
    from genesis_rl.adversaries.base import PolicyContext

    model = load_agent(run)
    assert type(model).__name__ == "RecurrentPPO"
    policy = AgentPolicy(PolicyContext(action_dim=1, seed=0, agent_path=run))
    obs = np.random.default_rng(0).uniform(-1, 1, (6, *model.observation_space.shape)).astype(np.float32)
    first = [policy.act(o) for o in obs]
    policy.reset(0, 0)
    again = [policy.act(o) for o in obs]
    assert np.array_equal(np.asarray(first), np.asarray(again))  # a reset memory: the same episode again
    forgetful = []
    for o in obs:  # the same observations with the memory dropped at every step
        policy.reset(0, 0)
        forgetful.append(policy.act(o))
    assert np.array_equal(first[0], forgetful[0])
    assert max(float(np.abs(f - g).max()) for f, g in zip(first[1:], forgetful[1:], strict=True)) > 1e-6

    out = tmp_path / "eval"
    assert main(["evaluate", "--agent", str(run), "--policies", "agent", "--scenes", "2", "--steps", "12",
                 "--no-report", "--quiet", "--out", str(out)]) == 0
    capsys.readouterr()
    assert json.loads((out / "summary.json").read_text())


def test_recurrent_settings_are_checked_and_a_file_cannot_claim_a_huge_memory(tmp_path) -> None:
    from genesis_rl.training.config import load_run_config

    config = tmp_path / "bad.toml"
    config.write_text(TINY_RECURRENT.replace("lstm_hidden_size = 16", "lstm_hidden_size = 0"))
    with pytest.raises(UserInputError, match="recurrent.lstm_hidden_size"):
        load_run_config(config)
    config.write_text(TINY_RECURRENT.replace("lstm_hidden_size = 16", "enable_critic_lstm = 1"))
    with pytest.raises(UserInputError, match="recurrent.enable_critic_lstm"):
        load_run_config(config)
    assert "[recurrent]" not in load_run_config(None).to_toml()  # other runs' files read as before

    run = _train(tmp_path, "run", "--steps", "16")
    agent = run / "agent.zip"
    with zipfile.ZipFile(agent) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    data = json.loads(members["data"])
    assert data["policy_kwargs"]["lstm_hidden_size"] == 16
    data["policy_kwargs"]["lstm_hidden_size"] = 10**9
    with zipfile.ZipFile(agent, "w") as zf:
        for name, blob in members.items():
            zf.writestr(name, json.dumps(data) if name == "data" else blob)
    from genesis_rl.adversaries import load_agent

    with pytest.raises(UserInputError, match=r"policy_kwargs\['lstm_hidden_size'\]"):
        load_agent(run)


def test_the_train_command_offers_every_learner_the_config_accepts() -> None:
    from genesis_rl.commands.train import ALGORITHMS as OFFERED
    from genesis_rl.training.config import ALGORITHMS

    assert OFFERED == ALGORITHMS


def test_a_recurrent_table_without_the_recurrent_learner_is_named_as_ignored(tmp_path) -> None:
    from genesis_rl.training.config import load_run_config

    config = tmp_path / "ablation.toml"
    config.write_text(TINY_RECURRENT)
    with pytest.warns(UserWarning, match=r"the \[recurrent\] table is ignored: train.algorithm = 'ppo'"):
        cfg = load_run_config(config, {"train": {"algorithm": "ppo"}})  # what --algorithm ppo does
    assert cfg.train.algorithm == "ppo" and "[recurrent]" not in cfg.to_toml()
