"""Cases the hostile sweep (tests/hostile/sweep_files.py) found after the family fixes were merged (issue 38):
each failed before its fix (a traceback, a hang, or an input accepted that would mix or mislead)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.odd.domain import load_odd


def test_an_empty_odd_file_is_refused(tmp_path) -> None:
    path = tmp_path / "odd.toml"
    path.write_text("")
    with pytest.raises(UserInputError, match="is empty; expected a name and at least one"):
        load_odd(path)


def test_a_port_list_with_an_empty_item_is_refused_naming_it(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["scenes", "--backend", "carla", "--count", "1", "--out", "c.json", "--carla-port", "2000,,2001"])
    assert stop.value.code == 2
    assert "'2000,,2001' has an empty item" in capsys.readouterr().err


def test_a_gif_stride_past_the_episode_is_refused_not_an_overflow(tmp_path) -> None:
    r = subprocess.run([sys.executable, "-m", "genesis_rl", "drive", "--steps", "5", "--system", "blind",
                        "--gif-stride", "1000000000000", "--out", str(tmp_path / "d")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "--gif-stride = 1000000000000; allowed: 1..5 (--steps)" in r.stderr


def test_resume_refuses_a_campaign_whose_episode_seeds_were_edited(tmp_path, capsys) -> None:
    camp = tmp_path / "camp"
    args = ["evaluate", "--policies", "sunny", "--system", "blind", "--map", "highway", "--scenes", "2",
            "--steps", "4", "--seed", "1", "--no-report", "--no-counterfactual", "--quiet", "--out", str(camp)]
    assert main(args) == 0
    meta = json.loads((camp / "campaign.json").read_text())
    meta["scenes"][0][1] += 1  # another episode seed under the campaign's name
    (camp / "campaign.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert main([*args, "--resume"]) == 2
    assert "field 'scenes' is not what seed 1 draws" in capsys.readouterr().err
    meta["scenes"][0][1] -= 1
    (camp / "campaign.json").write_text(json.dumps(meta))
    assert main([*args, "--resume"]) == 0  # restored: the campaign resumes (nothing left to run)


@pytest.mark.parametrize(("argv", "message"), [
    (["--executors", "ray,,local", "--workers", "1"], "--executors 'ray,,local'; allowed: a comma list of local, ray"),
    (["--workers", ",".join(["1"] * 40)], "--workers lists 40 counts; allowed: at most 16"),
])
def test_bench_campaign_lists_with_a_typo_or_too_many_runs_are_refused(capsys, argv, message) -> None:
    assert main(["bench", "campaign", "--scenes", "1", *argv]) == 2
    assert message in capsys.readouterr().err


def test_the_packages_warnings_are_one_line_naming_the_command(tmp_path) -> None:
    """A damaged episode on resume is set aside and run again, with one warning line (Python's format added the
    file, the line number and the source line of the warn call)."""
    camp = tmp_path / "camp"
    args = [sys.executable, "-m", "genesis_rl", "evaluate", "--policies", "sunny", "--system", "blind", "--map",
            "highway", "--scenes", "1", "--steps", "4", "--no-report", "--no-counterfactual", "--quiet", "--out",
            str(camp)]
    assert subprocess.run(args, capture_output=True, timeout=300).returncode == 0
    (next((camp / "episodes" / "sunny").glob("*.json"))).write_text("[" * 100_000)
    r = subprocess.run([*args, "--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("genesis-rl evaluate: warning: sunny scene_")
    assert " is damaged (episode file " in lines[0], lines


def test_an_empty_npz_is_a_damaged_file_not_an_eof_traceback(tmp_path) -> None:
    from genesis_rl.sut.perception.dataset import DetectionDataset

    empty = tmp_path / "data.npz"
    empty.write_bytes(b"")
    with pytest.raises(UserInputError, match="is not a genesis-rl detector dataset"):
        DetectionDataset.load(empty)
