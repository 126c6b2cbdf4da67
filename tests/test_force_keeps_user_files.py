"""``--force`` replaces only what genesis-rl wrote, below the top of the folder too: a user's file inside a folder
the tool fills (RUN/checkpoints/, RUN/tb/, CAMPAIGN/records/, an export's images/) is named and kept, and the
command is refused before anything is deleted."""

from __future__ import annotations

import json
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


# --- the manifest: --force deletes a file only when genesis-rl wrote exactly it -------------------------------

def _written_campaign(folder: Path) -> Path:
    """A campaign folder as the tool leaves it: marker, files named like its own, and the manifest the hold
    records as it lets the folder go."""
    from genesis_rl.core.files.output_folder import claim, replace

    with claim(folder, "campaign", force=False):
        replace(folder, "campaign")
        (folder / "summary.json").write_text('{"episodes": 1}')
        (folder / "records").mkdir()
        (folder / "records" / "agent_scene_0001.json").write_text("{}")
    return folder


def test_the_hold_records_what_it_wrote_with_sha256(tmp_path: Path) -> None:
    import hashlib

    from genesis_rl.core.files import manifest

    camp = _written_campaign(tmp_path / "camp")
    listing = manifest.read(camp)
    assert listing is not None and sorted(listing.files) == ["records/agent_scene_0001.json", "summary.json"]
    assert listing.files["summary.json"].sha256 == hashlib.sha256(b'{"episodes": 1}').hexdigest()
    assert foreign_entries(camp, "campaign") == []
    check_target(camp, "campaign", force=True)  # nothing of the user's: --force may go on


def test_force_refuses_a_file_of_ours_that_the_user_edited(tmp_path: Path) -> None:
    camp = _written_campaign(tmp_path / "camp")
    (camp / "summary.json").write_text('{"episodes": 1, "my note": "checked by hand"}')
    with pytest.raises(UserInputError, match=r"summary\.json \(changed since genesis-rl wrote it\)"):
        check_target(camp, "campaign", force=True)
    assert "my note" in (camp / "summary.json").read_text()


def test_force_refuses_a_users_file_under_one_of_our_names(tmp_path: Path) -> None:
    camp = _written_campaign(tmp_path / "camp")
    (camp / "records" / "agent_scene_0002.json").write_text('{"mine": true}')
    with pytest.raises(UserInputError, match=r"records/agent_scene_0002\.json \(not in the folder's manifest"):
        check_target(camp, "campaign", force=True)


def test_after_a_killed_run_force_names_what_the_manifest_does_not_list_and_says_resume(tmp_path: Path) -> None:
    """A run killed before it let the folder go leaves its lock file. Its last files and a user's edit since
    cannot be told apart, so --force names them (and says to --resume) rather than deleting a user's work."""
    from genesis_rl.core.files.output_folder import lock_path

    camp = _written_campaign(tmp_path / "camp")
    (camp / "summary.json").write_text('{"edited after the crash": 1}')
    lock_path(camp).write_text("12345\n")  # the killed writer's lock file, unlocked
    with pytest.raises(UserInputError, match=r"summary\.json \(changed since genesis-rl wrote it; the run writing "
                                             r"the folder was killed .*--resume it\)"):
        check_target(camp, "campaign", force=True)
    assert "edited after the crash" in (camp / "summary.json").read_text()


@pytest.mark.parametrize("damage", ["missing", "truncated", "deep", "link"])
def test_a_missing_or_damaged_manifest_refuses_force(tmp_path: Path, damage: str) -> None:
    """A marker of this version promises a manifest: without a readable one --force cannot tell a hand-edited
    file from ours, so it refuses (a folder of 0.30.0, whose marker promises none, is judged by names)."""
    from genesis_rl.core.files import manifest

    camp = _written_campaign(tmp_path / "camp")
    path = camp / manifest.MANIFEST
    if damage == "missing":
        path.unlink()
    elif damage == "truncated":
        path.write_text(path.read_text()[:20])
    elif damage == "deep":
        path.write_text("[" * 100_000 + "]" * 100_000)
    else:
        path.unlink()
        path.symlink_to(tmp_path / "elsewhere.json")
    with pytest.raises(UserInputError, match=r"\.genesis-rl\.manifest\.json \(missing or unreadable"):
        check_target(camp, "campaign", force=True)


def test_force_onto_a_hand_edited_report_in_a_campaign_is_refused(tmp_path: Path) -> None:
    from genesis_rl.core.files.output_paths import output_file

    camp = _written_campaign(tmp_path / "camp")
    output_file(camp / "report.html", force=False).write_text("<html>ours</html>")
    output_file(camp / "report.html", force=True).write_text("<html>ours again</html>")  # ours: replaced
    (camp / "report.html").write_text("<html>annotated by hand</html>")
    with pytest.raises(UserInputError, match=r"report\.html.*changed since genesis-rl wrote it"):
        output_file(camp / "report.html", force=True)
    assert "annotated" in (camp / "report.html").read_text()


def test_a_folder_without_a_manifest_is_judged_by_names_and_adopted_when_held(old: Path) -> None:
    from genesis_rl.core.files import manifest
    from genesis_rl.core.files.output_folder import hold

    camp = old / "camp"
    assert manifest.read(camp) is None and foreign_entries(camp, "campaign") == []
    with hold(camp):
        pass  # a command that wrote nothing (refused under the lock) leaves the folder as it was
    assert manifest.read(camp) is None
    with hold(camp):
        (camp / "summary.json").write_text("{}")  # a resume finishing it: its files of 0.29.0 adopted too
    listing = manifest.read(camp)
    assert listing is not None and "campaign.json" in listing.files and "summary.json" in listing.files


def test_report_into_a_campaign_is_listed_in_its_manifest(tmp_path: Path) -> None:
    from genesis_rl.core.files import manifest
    from genesis_rl.core.files.output_paths import output_file

    camp = _written_campaign(tmp_path / "camp")
    output_file(camp / "report.html", force=False).write_text("<html></html>")
    output_file(camp / "my_notes.html", force=False).write_text("<p>mine</p>")
    listing = manifest.read(camp)
    assert listing is not None and "report.html" in listing.files and "my_notes.html" not in listing.files
    assert foreign_entries(camp, "campaign") == ["my_notes.html"]


def test_drive_force_refuses_to_overwrite_an_edited_output(tmp_path: Path) -> None:
    from genesis_rl.core.files.output_folder import claim, write_marker

    out = tmp_path / "drive"
    with claim(out, "drive", force=False, files=["summary.json"]):
        out.mkdir()
        (out / "summary.json").write_text("{}")
        write_marker(out, "drive")
    check_target(out, "drive", force=True, files=["summary.json"])
    (out / "summary.json").write_text('{"edited": 1}')
    with pytest.raises(UserInputError, match=r"summary\.json \(changed since genesis-rl wrote it\)"):
        check_target(out, "drive", force=True, files=["summary.json"])


def test_evaluate_force_keeps_a_hand_edited_summary(old: Path, capsys) -> None:
    args = ["evaluate", "--agent", "run", "--policies", "random", "--catalog", "run/catalog.json", "--scenes", "1",
            "--steps", "5", "--out", "fresh", "--quiet", "--no-report"]
    assert main(args) == 0
    assert main([*args, "--force"]) == 0  # untouched: the tool's own files, replaced
    summary = old / "fresh" / "summary.json"
    summary.write_text(summary.read_text().replace("{", '{"reviewed": "yes", ', 1))
    assert main([*args, "--force"]) == 2
    assert "summary.json (changed since genesis-rl wrote it)" in capsys.readouterr().err
    assert '"reviewed": "yes"' in summary.read_text()


def _marker(folder: Path, kind: str, version: str = "0.30.0") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / ".genesis-rl.json").write_text(json.dumps({"schema": "genesis-rl/output-folder", "kind": kind,
                                                         "version": version}))


def test_a_folder_of_0_30_judges_the_folders_nested_in_its_own_by_their_names(tmp_path: Path) -> None:
    """A harden or benchmark folder of 0.30.0 has no manifest, so names decide; its round and campaign folders
    are its own, but a user's note in one is not: each nested genesis-rl folder is judged by its kind's names,
    and what harden writes beside them (round.json, weights/, near_misses/) by harden's."""
    hd = tmp_path / "hd"
    _marker(hd, "harden")
    (hd / "harden.json").write_text("{}")
    for rnd in ("round_0", "round_1"):
        (hd / rnd).mkdir()
        (hd / rnd / "round.json").write_text("{}")
        _marker(hd / rnd / "test", "campaign")
        (hd / rnd / "test" / "campaign.json").write_text("{}")
        (hd / rnd / "test" / "episodes" / "sunny").mkdir(parents=True)
        (hd / rnd / "test" / "episodes" / "sunny" / "scene_0003.json").write_text("{}")
    (hd / "round_1" / "weights").mkdir()
    (hd / "round_1" / "weights" / "detector.pt").write_bytes(b"w")
    (hd / "round_1" / "near_misses" / "frames").mkdir(parents=True)
    (hd / "round_1" / "near_misses" / "near_misses.json").write_text("{}")
    _marker(hd / "retest_4" / "round_1", "campaign")
    (hd / "retest_4" / "round_1" / "summary.json").write_text("{}")
    assert foreign_entries(hd, "harden") == []  # everything the tool writes passes

    (hd / "round_1" / "notes.txt").write_text("mine")
    (hd / "round_1" / "test" / "episodes" / "sunny" / "analysis.ipynb").write_text("mine")
    (hd / "retest_4" / "todo.md").write_text("mine")
    assert foreign_entries(hd, "harden") == ["retest_4/todo.md", "round_1/notes.txt",
                                             "round_1/test/episodes/sunny/analysis.ipynb"]
    with pytest.raises(UserInputError, match="round_1/notes.txt"):
        check_target(hd, "harden", force=True)
    assert (hd / "round_1" / "notes.txt").read_text() == "mine"

    bm = tmp_path / "bm"
    _marker(bm, "benchmark")
    _marker(bm / "campaigns" / "low_sun" / "trial_00", "campaign")
    (bm / "campaigns" / "low_sun" / "trial_00" / "campaign.json").write_text("{}")
    assert foreign_entries(bm, "benchmark") == []
    (bm / "campaigns" / "notes.txt").write_text("mine")
    assert foreign_entries(bm, "benchmark") == ["campaigns/notes.txt"]
