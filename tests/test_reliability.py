"""Nothing lost, nothing mixed (issue 21): --force replaces only our own folders, one writer per output
folder, training resumes exactly, and sizes that would exhaust memory or run for days are refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from builders import tiny_run

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError

TINY_RUN = tiny_run()  # 10-step episodes cross rollout boundaries: a checkpoint falls mid-episode


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


@pytest.mark.render
def test_env_processes_resume_exactly_with_the_fast_trainer(tmp_path, capsys) -> None:
    """With envs in subprocesses the trainer switches torch threads between rollouts and updates and runs the
    channels-last CNN with fused Adam (training/throughput.py): a run stopped at a checkpoint and resumed in
    a new process still ends with the uninterrupted run's weights, optimizer state and episodes, bit for bit."""
    import torch

    config = tmp_path / "tiny.toml"
    config.write_text(TINY_RUN.replace("torch_threads = 1", "torch_threads = 2\nenvs = 2"))
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main(["train", "--config", str(config), "--out", str(whole), "--quiet"]) == 0
    assert main(["train", "--config", str(config), "--out", str(cut), "--steps", "32", "--quiet"]) == 0
    assert main(["train", "--out", str(cut), "--resume", "--steps", "64", "--quiet"]) == 0
    capsys.readouterr()
    a, b = _weights(whole / "agent.zip"), _weights(cut / "agent.zip")
    assert "policy.features_extractor.cnn.0.weight" in a and a["optimizer.state.0.step"] == 4 * 2 * 2
    different = [k for k in a if isinstance(a[k], torch.Tensor) and not torch.equal(a[k], b[k])
                 or not isinstance(a[k], torch.Tensor) and a[k] != b[k]]
    assert different == []
    assert (cut / "episodes.csv").read_text() == (whole / "episodes.csv").read_text()
    assert torch.get_num_threads() == 2  # the update's threads are restored when training ends


# --- 1. --force replaces only a folder this tool wrote, never the command's input --------------------------

def _users_folder(path: Path) -> Path:
    path.mkdir()
    (path / "thesis.tex").write_text("years of work")
    return path


def test_train_force_refuses_a_folder_it_did_not_write(tmp_path, capsys) -> None:
    mine = _users_folder(tmp_path / "mine")
    assert main(["train", "--out", str(mine), "--force", "--system", "blind", "--scenes", "2", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"--force: '{mine}' is not a run folder written by genesis-rl (no .genesis-rl.json: thesis.tex)" in err
    assert (mine / "thesis.tex").read_text() == "years of work"
    assert [p.name for p in tmp_path.iterdir()] == ["mine"]  # and no lock file left beside it


def test_export_refuses_its_own_input_as_output(tmp_path, capsys) -> None:
    campaign = tmp_path / "camp"
    campaign.mkdir()
    (campaign / "campaign.json").write_text(json.dumps({"schema": "genesis-rl/campaign"}))
    for out, word in ((campaign, "is"), (tmp_path, "holds"), (campaign / "export", "lies inside")):
        assert main(["export", str(campaign), "--format", "coco", "--out", str(out), "--force"]) == 2
        assert f"--out '{out}' {word} this command's input '{campaign}'" in capsys.readouterr().err
    assert [p.name for p in campaign.iterdir()] == ["campaign.json"]


@pytest.mark.render
def test_drive_and_render_force_overwrite_only_in_their_own_folders(tmp_path, capsys) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "summary.json").write_text('{"my": "numbers"}')
    (mine / "rgb.png").write_text("my picture")
    (mine / "notes.txt").write_text("mine")
    assert main(["drive", "--scene", "0", "--steps", "2", "--system", "blind", "--out", str(mine), "--force",
                 "--no-gif", "--quiet"]) == 2
    assert "is not a drive folder written by genesis-rl (no .genesis-rl.json: notes.txt, rgb.png, summary.json)" \
        in capsys.readouterr().err
    assert main(["render", "--out", str(mine), "--force", "--width", "32", "--height", "24"]) == 2
    assert "refusing to overwrite files in it" in capsys.readouterr().err
    assert (mine / "summary.json").read_text() == '{"my": "numbers"}' and (mine / "rgb.png").read_text() == "my picture"
    # a folder render made itself is overwritten with --force; drive adds its files beside render's
    ours = tmp_path / "ours"
    for _ in range(2):
        assert main(["render", "--out", str(ours), "--force", "--width", "32", "--height", "24"]) == 0
    assert json.loads((ours / ".genesis-rl.json").read_text())["kind"] == "render"
    assert main(["drive", "--scene", "0", "--steps", "2", "--system", "blind", "--out", str(ours), "--no-gif",
                 "--quiet"]) == 0
    assert main(["drive", "--scene", "0", "--steps", "2", "--system", "blind", "--out", str(ours), "--no-gif",
                 "--quiet", "--force"]) == 2  # a render folder, not a drive folder
    capsys.readouterr()


def test_folders_of_genesis_rl_0_4_0_are_recognised_by_their_content(tmp_path) -> None:
    from genesis_rl.core.files import output_folder

    def folder(name: str, files: dict[str, str]) -> Path:
        path = tmp_path / name
        for rel, text in files.items():
            (path / rel).parent.mkdir(parents=True, exist_ok=True)
            (path / rel).write_text(text)
        return path

    run = folder("run", {"config.toml": "", "run.json": '{"package": "genesis-rl"}', "tb/x": ""})
    camp = folder("camp", {"campaign.json": '{"schema": "genesis-rl/campaign"}', "steps/sunny/scene_0000.parquet": ""})
    drive = folder("drive", {"summary.json": "{}", "telemetry_scene_0003.parquet": "", "drive_scene_0003.gif": ""})
    render = folder("render", {"rgb.png": "", "contact_sheet_urban.png": ""})
    export = folder("export", {"export.json": "{}", "metadata.jsonl": "", "images/a.jpg": ""})
    fake_run = folder("fake_run", {"config.toml": "", "run.json": '{"package": "other"}'})
    fake_render = folder("fake_render", {"rgb.png": "", "holiday.png": ""})
    fake_camp = folder("fake_camp", {"campaign.json": '{"schema": "something/else"}'})
    assert {p.name: output_folder.folder_kind(p) for p in (run, camp, drive, render, export, fake_run, fake_render,
                                                           fake_camp)} == {
        "run": "run", "camp": "campaign", "drive": "drive", "render": "render", "export": "export",
        "fake_run": None, "fake_render": None, "fake_camp": None}
    output_folder.check_target(camp, "campaign", force=True)  # replaceable
    with pytest.raises(UserInputError, match="holds a genesis-rl run output.*is it a training run"):
        output_folder.check_target(run, "campaign", force=True)
    with pytest.raises(UserInputError, match="no .genesis-rl.json: campaign.json"):
        output_folder.check_target(fake_camp, "campaign", force=True)


# --- 2. one writer per output folder ------------------------------------------------------------------------

_HOLDER = """
import sys, time
from pathlib import Path
from genesis_rl.core.files import output_folder
with output_folder.hold(Path(sys.argv[1])):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def _start_holder(folder: Path, seconds: float) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", _HOLDER, str(folder), str(seconds)], stdout=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_and_a_killed_writers_lock_is_taken_over(tmp_path) -> None:
    from genesis_rl.core.files import output_folder

    folder = tmp_path / "out"
    holder = _start_holder(folder, 60)
    try:
        with pytest.raises(UserInputError, match=rf"output folder '{folder}' is being written by another "
                                                 rf"genesis-rl process \(pid {holder.pid}\)"):
            with output_folder.claim(folder, "drive", force=False, files=["summary.json"]):
                pass
    finally:
        holder.kill()  # SIGKILL: no clean-up runs, the lock file stays
        holder.wait()
    assert output_folder.lock_path(folder).read_text().strip() == str(holder.pid)
    with output_folder.claim(folder, "drive", force=False, files=["summary.json"]):
        assert output_folder.lock_path(folder).read_text().strip() == str(os.getpid())
    assert not output_folder.lock_path(folder).exists()  # released and removed


@pytest.mark.render
def test_two_evaluate_runs_into_one_folder_do_not_mix(tmp_path) -> None:
    from genesis_rl.core.files import output_folder

    catalog = tmp_path / "cat.json"
    assert main(["scenes", "--map", "highway", "--count", "2", "--out", str(catalog), "--quiet"]) == 0
    out = tmp_path / "campaign"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}

    def evaluate(policy: str, steps: int) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "genesis_rl", "evaluate", "--policies", policy, "--catalog",
                                 str(catalog), "--scenes", "1", "--steps", str(steps), "--system", "blind", "--out",
                                 str(out), "--no-report", "--quiet", "--force"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)

    first = evaluate("random", 48)
    lock = output_folder.lock_path(out)
    for _ in range(600):
        if lock.exists() or first.poll() is not None:
            break
        time.sleep(0.05)
    second = evaluate("sunny", 32)
    _, err = second.communicate(timeout=120)
    assert second.returncode == 2
    assert f"output folder '{out}' is being written by another genesis-rl process (pid {first.pid})" in err
    assert first.wait(timeout=300) == 0
    spec = json.loads((out / "campaign.json").read_text())["spec"]
    assert (spec["policies"], spec["steps"]) == (["random"], 48)
    assert [p.name for p in (out / "episodes").iterdir()] == ["random"]
    assert not lock.exists()


# --- 7. sizes and counts that would exhaust memory or run for days ------------------------------------------

@pytest.mark.parametrize(("argv", "message"), [
    (["drive", "--scene", "0:1000000000000"],
     "--scene '0:1000000000000' needs 1,000,000,000,000 scenes, over the limit of 100,000 scenes"),
    (["scenes", "--count", "1000000000000"], "--count = 1,000,000,000,000, over the limit of 100,000 scenes"),
    (["render", "--warmup", "100000000000"], "--warmup = 100,000,000,000, over the limit of 100,000 simulation"),
    (["drive", "--steps", "100000000"], "--steps = 100,000,000, over the limit of 100,000 simulation steps"),
    (["train", "--steps", str(10**26)], "train.total_timesteps = 100,000,000,000,000,000,000,000,000, over the "
                                        "limit of 100,000,000 env steps"),
])
def test_sizes_that_would_run_for_days_are_refused(tmp_path, capsys, argv, message) -> None:
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and "set GENESIS_RL_MAX_" in err and "to raise it" in err
    assert not (tmp_path / "out").exists()


def test_a_limit_is_raised_by_its_environment_variable(monkeypatch) -> None:
    from genesis_rl.training.config import load_run_config

    with pytest.raises(UserInputError, match="GENESIS_RL_MAX_TIMESTEPS"):
        load_run_config(None, {"train": {"total_timesteps": 200_000_000}})
    monkeypatch.setenv("GENESIS_RL_MAX_TIMESTEPS", "300000000")
    assert load_run_config(None, {"train": {"total_timesteps": 200_000_000}}).train.total_timesteps == 200_000_000
    monkeypatch.setenv("GENESIS_RL_MAX_TIMESTEPS", "many")
    with pytest.raises(UserInputError, match="GENESIS_RL_MAX_TIMESTEPS = 'many' must be an integer"):
        load_run_config(None)


def test_ctrl_c_while_the_command_line_imports_is_one_line(monkeypatch, capsys) -> None:
    """The hostile sweep's one traceback: Ctrl-C during the start-up imports (before cli.main's handler)."""
    import sys

    from genesis_rl.commands import entry

    class Interrupt:  # a meta-path finder that is "interrupted" while genesis_rl.commands.cli imports
        def find_spec(self, name, path=None, target=None):
            if name == "genesis_rl.commands.cli":
                raise KeyboardInterrupt
            return None

    monkeypatch.delitem(sys.modules, "genesis_rl.commands.cli", raising=False)
    monkeypatch.setattr(sys, "meta_path", [Interrupt(), *sys.meta_path])
    assert entry.main() == 130
    assert capsys.readouterr().err == "interrupted\n"


TINY_SAC = tiny_run(env={"observation": "features", "obs_history": 2, "obs_width": None, "obs_height": None},
                    ppo={"n_steps": None, "batch_size": None, "n_epochs": None},
                    train={"algorithm": "sac", "total_timesteps": 64},
                    sac={"buffer_size": 100, "learning_starts": 8, "batch_size": 8})


def _sac_state(path: Path) -> dict:
    from stable_baselines3 import SAC

    model = SAC.load(path, device="cpu")
    return {**{f"policy.{k}": v for k, v in model.policy.state_dict().items()},
            **{f"actor_opt.{k}": v for k, v in _flat(model.actor.optimizer.state_dict()).items()},
            **{f"critic_opt.{k}": v for k, v in _flat(model.critic.optimizer.state_dict()).items()},
            "log_ent_coef": model.log_ent_coef.detach().clone()}


def test_a_resumed_sac_run_matches_an_uninterrupted_one(tmp_path, capsys) -> None:
    """SAC (train.algorithm = "sac") learns from a replay buffer: a checkpoint keeps it, so a run stopped at
    step 32 and resumed ends with the uninterrupted run's weights, optimizers, entropy coefficient and
    episodes, bit for bit; only the newest buffer is kept on disk."""
    import torch

    config = tmp_path / "sac.toml"
    config.write_text(TINY_SAC)
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main(["train", "--config", str(config), "--out", str(whole), "--quiet"]) == 0
    assert main(["train", "--config", str(config), "--out", str(cut), "--steps", "32", "--quiet"]) == 0
    assert [p.name for p in (cut / "checkpoints").glob("*.replay.npz")] == ["step_00000032.replay.npz"]
    assert main(["train", "--out", str(cut), "--resume", "--steps", "64", "--quiet"]) == 0
    capsys.readouterr()
    a, b = _sac_state(whole / "agent.zip"), _sac_state(cut / "agent.zip")
    assert "policy.actor.mu.weight" in a and "policy.critic_target.qf0.0.weight" in a
    assert a["actor_opt.state.0.step"] == 64 - 8  # one update a step after the 8 warm-up steps
    different = [k for k in a if isinstance(a[k], torch.Tensor) and not torch.equal(a[k], b[k])
                 or not isinstance(a[k], torch.Tensor) and a[k] != b[k]]
    assert different == []
    assert float(a["log_ent_coef"]) != 0.0  # the entropy coefficient was learned (it starts at log 1 = 0)
    assert (cut / "episodes.csv").read_text() == (whole / "episodes.csv").read_text()
    # the loose replay buffer is what resume needs: without it the run says so, exit 2
    for p in (cut / "checkpoints").glob("*.replay.npz"):
        p.unlink()
    assert main(["train", "--out", str(cut), "--resume", "--steps", "80", "--quiet"]) == 2
    assert "replay.npz missing" in capsys.readouterr().err


def test_evaluate_plays_a_sac_agent(tmp_path, capsys) -> None:
    """The agent policy loads a SAC run (its config names the learner) and keeps its actions in the box."""
    config = tmp_path / "sac.toml"
    config.write_text(TINY_SAC.replace("total_timesteps = 64", "total_timesteps = 16", 1))
    run = tmp_path / "run"
    assert main(["train", "--config", str(config), "--out", str(run), "--quiet"]) == 0
    from genesis_rl.adversaries import load_agent

    model = load_agent(run)
    assert type(model).__name__ == "SAC"
    loose = tmp_path / "loose.zip"  # no run config beside it: only through pickle, so only when trusted
    loose.write_bytes((run / "agent.zip").read_bytes())
    with pytest.raises(UserInputError, match="--trust-pickle"):
        load_agent(loose)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("GENESIS_RL_TRUST_PICKLE", "1")  # what --trust-pickle sets: tried as PPO, then as SAC
        assert type(load_agent(loose)).__name__ == "SAC"
    out = tmp_path / "eval"
    assert main(["evaluate", "--agent", str(run), "--policies", "agent", "--scenes", "2", "--steps", "12",
                 "--no-report", "--quiet", "--out", str(out)]) == 0
    capsys.readouterr()
    assert (out / "summary.json").is_file()
