"""Cases a later hostile sweep found in shared readers (an ``.npz`` header, a ``--nominal`` file, a record's
system, a benchmark's finished trial) and in the counts of ``harden`` and ``estimate --weights``: each was a
traceback, a run without end, or an input kept that would mix results, before its fix."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError


def _npz_claiming(path: Path, member: str, shape: tuple[int, ...]) -> None:
    """An ``.npz`` whose ``member`` header claims ``shape`` of float32 and holds 16 bytes."""
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f4", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(f"{member}.npy", head.getvalue() + b"\0" * 16)  # the header writer adds the magic


@pytest.mark.parametrize("shape", [(10**12,), (10**6, 10**6)])
def test_a_replay_buffer_whose_header_claims_a_huge_shape_is_refused_naming_the_member(tmp_path, shape) -> None:
    from gymnasium import spaces
    from stable_baselines3.common.buffers import ReplayBuffer

    from genesis_rl.training.safe_load import read_replay_buffer

    buffer = ReplayBuffer(8, spaces.Box(0, 1, (3,), np.float32), spaces.Box(-1, 1, (2,), np.float32), "cpu")
    path = tmp_path / "replay.npz"
    _npz_claiming(path, "observations", shape)
    with pytest.raises(UserInputError, match=r"replay buffer '.*replay.npz' is damaged \(member 'observations' "
                                             r"claims shape .* 4,000,000,000,000 bytes"):
        read_replay_buffer(path, buffer)


def test_an_sb3_state_whose_header_claims_a_huge_shape_is_refused_naming_the_member(tmp_path) -> None:
    from genesis_rl.env.genesis_env import EnvConfig
    from genesis_rl.training.config import RunConfig
    from genesis_rl.training.safe_load import read_sb3_state

    path = tmp_path / "step_8.sb3.npz"
    _npz_claiming(path, "last_obs", (10**12,))
    cfg = RunConfig(env=EnvConfig(system="blind"))
    with pytest.raises(UserInputError, match=r"checkpoint file '.*step_8.sb3.npz' is damaged \(member 'last_obs' "
                                             r"claims shape \[1000000000000\]"):
        read_sb3_state(path, cfg, 1)


def test_a_deeply_nested_nominal_file_is_refused_not_a_recursion_error(tmp_path) -> None:
    from genesis_rl.estimation.nominal import load_starts

    path = tmp_path / "n.toml"
    path.write_text("x = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(UserInputError, match=r"--nominal '.*n.toml'.*nest"):
        load_starts(path)


def test_a_record_whose_system_kwargs_is_a_list_is_refused_naming_the_field() -> None:
    from genesis_rl.campaigns.records import load_recorded_system

    with pytest.raises(UserInputError, match=r"field 'system.kwargs' = .*allowed: an object"):
        load_recorded_system({"spec": "blind", "kwargs": [1, 2]})


@pytest.mark.parametrize(("flag", "message"), [
    ("--rounds", "--rounds = 1,000,000,000,000, over the limit of 100 rounds"),
    ("--clear-frames", "--clear-frames = 1,000,000,000,000, over the limit of 100,000 frames"),
])
def test_harden_counts_past_their_ceilings_are_refused(tmp_path, capsys, flag, message) -> None:
    assert main(["harden", str(tmp_path / "camp"), "--out", str(tmp_path / "h"), flag, str(10**12)]) == 2
    assert message in capsys.readouterr().err


def test_estimate_weights_for_a_member_without_a_detector_is_refused_before_any_episode(tmp_path, capsys) -> None:
    weights = tmp_path / "w.pt"
    weights.write_bytes(b"not read")
    assert main(["estimate", "--member", "oracle_highway", "--weights", str(weights), "--episodes", "2",
                 "--out", str(tmp_path / "e")]) == 2
    err = capsys.readouterr().err
    assert f"--weights '{weights}': member 'oracle_highway' runs system 'oracle', which takes no weights" in err
    assert not (tmp_path / "e").exists()


def test_a_benchmark_keeps_no_finished_trial_whose_episode_seeds_were_edited(tmp_path) -> None:
    from genesis_rl.campaigns.campaign_folder import check_finished_campaign
    from genesis_rl.campaigns.campaign_spec import CampaignSpec

    camp = tmp_path / "camp"
    assert main(["evaluate", "--policies", "sunny", "--system", "blind", "--map", "highway", "--scenes", "2",
                 "--steps", "4", "--seed", "1", "--no-report", "--no-counterfactual", "--quiet",
                 "--out", str(camp)]) == 0
    meta = json.loads((camp / "campaign.json").read_text())
    spec = CampaignSpec.from_json(meta["spec"])
    check_finished_campaign(spec, camp)  # as written: kept
    meta["scenes"][1][1] += 1  # another episode seed under the trial's name
    (camp / "campaign.json").write_text(json.dumps(meta))
    with pytest.raises(UserInputError, match=r"'.*campaign.json' field 'scenes' is not what seed 1 draws"):
        check_finished_campaign(spec, camp)
