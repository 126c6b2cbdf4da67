"""Opening a run someone else made runs none of their code (issue 38, family 2): an agent's or checkpoint's
pickled entries are never unpickled, a replay buffer is plain arrays, and an import path a file names is
imported only when the command line names its module (docs/reliability.md, "Safe loading")."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import pickle
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from builders import tiny_run

from genesis_rl.commands.cli import main

PLUGINS = Path(__file__).parent / "plugins"

#: the tiny run with a features observation and a [sac] table, its learner named by ALGO
TINY = tiny_run(env={"observation": "features", "obs_history": 2, "obs_width": None, "obs_height": None},
                train={"algorithm": "ALGO", "total_timesteps": 32},
                sac={"buffer_size": 100, "learning_starts": 8, "batch_size": 8})


class _Payload:
    """Unpickling it creates ``path``: the marker that code from the file ran."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self):  # noqa: ANN204
        return (os.mkdir, (self.path,))


def _pickled(marker: Path) -> dict[str, str]:
    return {":type:": "<class 'function'>", ":serialized:": base64.b64encode(pickle.dumps(_Payload(marker))).decode()}


def _poison_zip(path: Path, marker: Path) -> None:
    """Put the payload under every key SB3 pickles (and one it does not know), as a colleague's crafted
    agent.zip would; the tensors stay as they are."""
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    data = json.loads(members["data"])
    for key, value in list(data.items()):
        if isinstance(value, dict) and ":serialized:" in value:
            data[key] = _pickled(marker)
    data["something_new"] = _pickled(marker)
    data["env"] = "no_such_module_xyz:Env"  # SB3 would gym.make() a string env, importing its module
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as z:
        for name, blob in members.items():
            z.writestr(name, blob)


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> str:
    """Three highway scenes: the default test catalog (1,199 scenes) takes most of a small campaign's time."""
    path = tmp_path_factory.mktemp("catalog") / "highway.json"
    assert main(["scenes", "--map", "highway", "--count", "3", "--out", str(path), "--quiet"]) == 0
    return str(path)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A tiny PPO run (finished) and a tiny SAC run stopped at its step-16 checkpoint."""
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for algo, steps in (("ppo", "32"), ("sac", "16")):
        config = root / f"{algo}.toml"
        config.write_text(TINY.replace("ALGO", algo))
        out[algo] = root / algo
        assert main(["train", "--config", str(config), "--out", str(out[algo]), "--steps", steps, "--quiet"]) == 0
    return out


def _copy_run(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_a_pickled_payload_in_an_agent_zip_is_never_run(runs, catalog, tmp_path, capsys) -> None:
    """SB3 keeps the policy class, spaces and schedules pickled in agent.zip's data; a crafted one ran its
    payload on ``evaluate --agent`` (exit 0). The agent is rebuilt from its run's config instead: the payload
    never runs, and the agent acts with the file's own weights."""
    import torch
    from stable_baselines3.common.save_util import load_from_zip_file

    from genesis_rl.adversaries import load_agent

    run = _copy_run(runs["ppo"], tmp_path / "shared")
    marker = tmp_path / "ran"
    _poison_zip(run / "agent.zip", marker)
    model = load_agent(run)
    assert not marker.exists()
    _, params, _ = load_from_zip_file(run / "agent.zip", load_data=False, device="cpu")
    state = model.policy.state_dict()
    assert len(state) > 4 and all(torch.equal(state[k], params["policy"][k]) for k in state)
    action, _ = model.predict(np.full(model.observation_space.shape, 0.5, np.float32), deterministic=True)
    assert action.shape == (5,) and np.all(np.abs(action) <= 1)
    # and through the command line, which loads it in the parent and in the worker
    assert main(["evaluate", "--agent", str(run), "--policies", "agent", "--scenes", "1", "--steps", "4",
                 "--catalog", catalog, "--no-report", "--quiet", "--out", str(tmp_path / "eval")]) == 0
    capsys.readouterr()
    assert not marker.exists()
    assert (tmp_path / "eval" / "summary.json").is_file()


def test_an_agent_without_its_run_config_loads_only_with_trust_pickle(runs, tmp_path, capsys) -> None:
    """A loose agent.zip has no config to rebuild it from: it is refused, naming --trust-pickle and why."""
    loose = tmp_path / "loose.zip"
    loose.write_bytes((runs["ppo"] / "agent.zip").read_bytes())
    marker = tmp_path / "ran"
    _poison_zip(loose, marker)
    from genesis_rl.adversaries import load_agent
    from genesis_rl.core.errors import UserInputError

    with pytest.raises(UserInputError, match=r"no run config.toml beside it .* --trust-pickle .* runs any code"):
        load_agent(loose)
    assert not marker.exists()


def test_a_crafted_checkpoint_resumes_without_running_its_payload(runs, tmp_path, capsys) -> None:
    """``train --resume`` loaded the checkpoint's zip through pickle; now its pickled entries are never read
    (the last observation comes from step_N.sb3.npz, the replay buffer from step_N.replay.npz) and the run
    resumes to its end."""
    run = _copy_run(runs["sac"], tmp_path / "shared")
    marker = tmp_path / "ran"
    ck = run / "checkpoints"
    _poison_zip(ck / "step_00000016.zip", marker)
    code = main(["train", "--out", str(run), "--resume", "--steps", "32", "--quiet"])
    capsys.readouterr()
    assert not marker.exists()
    assert code == 0
    assert sorted(p.name for p in ck.glob("step_00000016.*")) == [
        "step_00000016.sb3.npz", "step_00000016.state.json", "step_00000016.zip"]  # the newest buffer only
    with np.load(ck / "step_00000032.replay.npz", allow_pickle=False) as z:
        assert int(z["pos"]) == 32 and z["observations"].shape == (100, 1, 32)
    assert json.loads((ck / "last.json").read_text())["timesteps"] == 32


def test_a_pickled_replay_buffer_or_old_checkpoint_needs_trust_pickle(runs, tmp_path, capsys) -> None:
    """A checkpoint of genesis-rl 0.10.0 kept SAC's buffer as ``step_N.replay.pkl`` (SB3's pickle): resuming
    it unpickled whatever it held. It is refused now, exit 2, naming --trust-pickle; nothing ran."""
    run = _copy_run(runs["sac"], tmp_path / "shared")
    marker = tmp_path / "ran"
    ck = run / "checkpoints"
    for p in ck.glob("step_00000016.replay.*"):
        p.unlink()
    (ck / "step_00000016.replay.pkl").write_bytes(pickle.dumps(_Payload(marker)))
    assert main(["train", "--out", str(run), "--resume", "--steps", "32", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "step_00000016.replay.pkl" in err and "--trust-pickle" in err and "runs any code" in err
    assert not marker.exists()
    # a 0.10.0 checkpoint (its last observation only pickled in the zip) says the same
    run = _copy_run(runs["sac"], tmp_path / "older")
    (run / "checkpoints" / "step_00000016.sb3.npz").unlink()
    assert main(["train", "--out", str(run), "--resume", "--steps", "32", "--quiet"]) == 2
    assert "--trust-pickle" in capsys.readouterr().err


def _evil_module(tmp_path: Path, monkeypatch, name: str) -> Path:
    """A module on the path whose import creates a marker (a shared run folder can carry one: the current
    folder is on the path of ``python -m``)."""
    marker = tmp_path / f"{name}.ran"
    (tmp_path / f"{name}.py").write_text(
        f"from pathlib import Path\nPath({str(marker)!r}).mkdir()\n"
        "from genesis_rl.sut.system.builtin import BlindSystem as System\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, name, raising=False)
    return marker


@pytest.mark.parametrize("key", ["system", "plugins"])
def test_an_import_path_in_a_config_file_is_refused_unless_the_command_line_names_it(catalog, tmp_path, monkeypatch,
                                                                                     capsys, key) -> None:
    """``env.system = "mod:Class"`` or ``env.plugins = ["mod"]`` in a file (a run's config.toml, a shared
    config) imported ``mod``, running its code. It is refused, exit 2, naming --plugin; with ``--plugin mod``
    on the command line the module is the user's choice and loads."""
    marker = _evil_module(tmp_path, monkeypatch, f"evil_{key}")
    value = f'"evil_{key}:System"' if key == "system" else f'["evil_{key}"]'
    config = tmp_path / "shared.toml"
    config.write_text(f"[env]\n{key} = {value}\n")
    args = ["evaluate", "--config", str(config), "--policies", "sunny", "--scenes", "1", "--steps", "4",
            "--catalog", catalog, "--no-report", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert f"module 'evil_{key}' is not one the command line names" in err and f"--plugin evil_{key}" in err
    assert not marker.exists()
    assert main([*args, "--out", str(tmp_path / "b"), "--plugin", f"evil_{key}"]) == 0
    capsys.readouterr()
    assert marker.exists()


def test_an_import_path_in_a_campaign_json_or_a_run_config_is_refused(runs, catalog, tmp_path, monkeypatch,
                                                                      capsys) -> None:
    """A shared campaign.json (``reactivity --campaign``) or a run's config.toml (``evaluate --agent``) that
    names a module of its own is refused before anything imports it."""
    marker = _evil_module(tmp_path, monkeypatch, "evil_camp")
    camp = tmp_path / "camp"
    assert main(["evaluate", "--policies", "sunny", "--scenes", "2", "--steps", "4", "--no-report", "--quiet",
                 "--catalog", catalog, "--out", str(camp)]) == 0
    meta = json.loads((camp / "campaign.json").read_text())
    meta["spec"]["env"]["plugins"] = ["evil_camp"]
    (camp / "campaign.json").write_text(json.dumps(meta))
    assert main(["reactivity", "--campaign", str(camp), "--policy", "sunny", "--quiet"]) == 2
    assert "--plugin evil_camp" in capsys.readouterr().err
    run = _copy_run(runs["ppo"], tmp_path / "run")
    text = (run / "config.toml").read_text().replace('system = "blind"', 'system = "evil_camp:System"')
    assert "evil_camp" in text
    (run / "config.toml").write_text(text)
    meta = json.loads((run / "run.json").read_text())  # whoever shares a run can re-pin it: pins are no signature
    meta["pins"]["config.toml"]["sha256"] = hashlib.sha256((run / "config.toml").read_bytes()).hexdigest()
    (run / "run.json").write_text(json.dumps(meta))
    assert main(["evaluate", "--agent", str(run), "--policies", "agent", "--scenes", "1", "--steps", "4",
                 "--catalog", catalog, "--no-report", "--quiet", "--out", str(tmp_path / "eval")]) == 2
    assert "--plugin evil_camp" in capsys.readouterr().err
    assert not marker.exists()


def test_a_rule_by_import_path_loads_from_the_command_line(catalog, tmp_path, monkeypatch, capsys) -> None:
    """docs/extending.md's rule by import path in a rulebook TOML: refused when only the file names it, run
    when ``--plugin`` (or GENESIS_RL_PLUGINS) names its module."""
    monkeypatch.syspath_prepend(str(PLUGINS))
    rulebook = tmp_path / "rulebook.toml"
    rulebook.write_text('[[rules]]\nname = "collision"\n\n[[rules]]\nname = "user_extensions:Speeding"\n'
                        '\n[[rules]]\nname = "proximity"\n')
    config = tmp_path / "c.toml"
    config.write_text(f"[env]\nrulebook = {str(rulebook)!r}\n")
    args = ["evaluate", "--config", str(config), "--policies", "sunny", "--scenes", "1", "--steps", "4",
            "--catalog", catalog, "--no-report", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 2
    assert "--plugin user_extensions" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "b"), "--plugin", "user_extensions"]) == 0
    monkeypatch.setenv("GENESIS_RL_PLUGINS", "user_extensions")
    assert main([*args, "--out", str(tmp_path / "c")]) == 0
    capsys.readouterr()
    row = json.loads(next((tmp_path / "c" / "episodes" / "sunny").glob("*.json")).read_text())
    assert list(row["violations"]) == ["collision", "speeding", "proximity"]
    # reporting the shared campaign needs none of its code: the rule as stored (name, unit) is enough
    monkeypatch.delenv("GENESIS_RL_PLUGINS")
    assert main(["report", str(tmp_path / "c"), "--force"]) == 0
    capsys.readouterr()
    assert "speeding [m/s]" in (tmp_path / "c" / "report.html").read_text()


def test_an_import_path_in_a_record_is_refused(tmp_path, monkeypatch, capsys) -> None:
    """A shared edge-case record names its system and its rules; ``replay`` imported an import path found
    there. It is refused before anything is imported, naming --plugin."""
    marker = _evil_module(tmp_path, monkeypatch, "evil_rec")
    source = Path(__file__).parent / "data" / "campaign_0.4.0" / "records" / "sunny_scene_0000.json"
    record = json.loads(source.read_text())
    record["system"]["spec"] = "evil_rec:System"
    path = tmp_path / "record.json"
    path.write_text(json.dumps(record))
    assert main(["replay", str(path), "--out", str(tmp_path / "r1"), "--no-gif", "--quiet"]) == 2
    assert "--plugin evil_rec" in capsys.readouterr().err
    record = json.loads(source.read_text())
    record["rulebook"][2] = {"priority": 3, "name": "speeding", "params": {}, "path": "evil_rec:System"}
    path.write_text(json.dumps(record))
    assert main(["replay", str(path), "--out", str(tmp_path / "r2"), "--no-gif", "--quiet"]) == 2
    assert "--plugin evil_rec" in capsys.readouterr().err
    assert not marker.exists()


def test_yolo_weights_a_file_names_are_not_unpickled(tmp_path) -> None:
    """A YOLO .pt file is a pickle (ultralytics loads it so): a weights path read from a run's config, a
    campaign or a record is refused unless the command line names it (--weights) or --trust-pickle."""
    import argparse

    from genesis_rl.core.errors import UserInputError
    from genesis_rl.core.trust import check_pickle_file, trusted_for
    from genesis_rl.sut.system.yolo_adapter import YoloSystem

    marker = tmp_path / "ran"
    weights = tmp_path / "shared.pt"
    weights.write_bytes(pickle.dumps(_Payload(marker)))
    with trusted_for(argparse.Namespace()), pytest.raises(UserInputError, match="runs any code it holds"):
        YoloSystem(weights=str(weights))
    assert not marker.exists()
    with trusted_for(argparse.Namespace(weights=str(weights))):
        check_pickle_file(weights, "YOLO weights file")  # named now: the user's choice
    with trusted_for(argparse.Namespace(trust_pickle=True)):
        check_pickle_file(weights, "YOLO weights file")


def test_an_agent_naming_a_class_outside_the_allow_list_is_refused(runs, tmp_path, monkeypatch) -> None:
    """The network's classes are read from the readable copy SB3 stores beside its pickle, by full name from a
    fixed list: a file naming another class (here a module that would run code at import) is refused, naming
    --trust-pickle, and nothing is imported."""
    from genesis_rl.adversaries import load_agent
    from genesis_rl.core.errors import UserInputError

    marker = _evil_module(tmp_path, monkeypatch, "evil_kwargs")
    run = _copy_run(runs["ppo"], tmp_path / "shared")
    zip_path = run / "agent.zip"
    with zipfile.ZipFile(zip_path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    data = json.loads(members["data"])
    data["policy_kwargs"] = {**_pickled(tmp_path / "ran"), "features_extractor_class": "<class 'evil_kwargs.System'>"}
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(zip_path, "w") as z:
        for name, blob in members.items():
            z.writestr(name, blob)
    with pytest.raises(UserInputError, match=r"policy_kwargs\['features_extractor_class'\].*--trust-pickle"):
        load_agent(run)
    assert not marker.exists() and not (tmp_path / "ran").exists()
