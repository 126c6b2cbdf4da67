"""``--force`` replaces only what genesis-rl wrote, below the top of the folder too: a user's file inside a folder
the tool fills (RUN/checkpoints/, RUN/tb/, CAMPAIGN/records/, an export's images/) is named and kept, and the
command is refused before anything is deleted."""

from __future__ import annotations

from pathlib import Path

import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.output_folder import check_target, foreign_entries


@pytest.fixture()
def old(v029: Path) -> Path:
    return v029


def test_the_tools_own_files_below_the_top_are_not_foreign(old: Path) -> None:
    ck = old / "run" / "checkpoints"
    ck.mkdir()
    for name in ("step_00000016.zip", "step_00000016.sb3.npz", "step_00000016.state.json", "last.zip",
                 "last.json", ".last.zip.a1b2c3d4tmp"):
        (ck / name).write_bytes(b"x")
    (old / "run" / "tb" / "PPO_1").mkdir(parents=True)
    (old / "run" / "tb" / "PPO_1" / "events.out.tfevents.1.vm.1.0").write_bytes(b"x")
    assert foreign_entries(old / "run", "run") == []
    assert foreign_entries(old / "camp", "campaign") == []


@pytest.mark.parametrize(("kind", "where", "user_file"), [
    ("run", "run", "checkpoints/notes.txt"),
    ("run", "run", "tb/my_plots/figure.png"),
    ("campaign", "camp", "records/my_analysis.json"),
    ("campaign", "camp", "episodes/agent/notes.md"),
])
def test_force_names_a_users_file_inside_an_own_folder_and_deletes_nothing(old: Path, kind: str, where: str,
                                                                           user_file: str) -> None:
    path = old / where / user_file
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("years of work")
    before = sorted(p.relative_to(old) for p in old.rglob("*"))
    with pytest.raises(UserInputError, match=f"also holds what genesis-rl did not write there: {user_file}"):
        check_target(old / where, kind, force=True)
    assert path.read_text() == "years of work" and sorted(p.relative_to(old) for p in old.rglob("*")) == before


def test_evaluate_force_keeps_an_analysis_in_records(old: Path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(old)
    (old / "camp" / "records" / "my_analysis.json").write_text("{}")
    assert main(["evaluate", "--agent", "run", "--policies", "random", "--catalog", "run/catalog.json", "--scenes",
                 "1", "--steps", "5", "--out", "camp", "--force", "--quiet"]) == 2
    assert "records/my_analysis.json" in capsys.readouterr().err
    assert (old / "camp" / "records" / "my_analysis.json").exists()
    assert (old / "camp" / "records" / "agent_scene_0001.json").exists()  # nothing of the campaign went either
