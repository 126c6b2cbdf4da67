"""One output rule for every command (issue 38, family 1): an output never lands on the command's own input,
'-' and /dev/stdout write to standard output, a FIFO is written in place, a link or a device is never replaced
by a regular file, and --force on a run or campaign folder removes only what genesis-rl wrote there."""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
import time
from pathlib import Path

import pytest
from builders import tiny_run

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import io_utils, output_folder

TINY_RUN = tiny_run(env={"map": None, "scenes": 2, "episode_steps": 8}, ppo={"n_epochs": 1},
                    train={"total_timesteps": 16, "seed": None})


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("camp")
    assert main(["scenes", "--count", "2", "--out", str(folder / "cat.json"), "--quiet"]) == 0
    assert main(["evaluate", "--catalog", str(folder / "cat.json"), "--policies", "random,sunny", "--scenes", "1",
                 "--steps", "5", "--system", "blind", "--out", str(folder / "camp"), "--quiet", "--no-report"]) == 0
    return folder / "camp"


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture()
def camp(campaign, tmp_path) -> Path:
    copy = tmp_path / "camp"
    shutil.copytree(campaign, copy)
    return copy


# --- an output never lands on an input -----------------------------------------------------------------------

@pytest.mark.parametrize(("argv", "out", "onto"), [
    (["report", "{c}", "--force", "--out"], "campaign.json", "campaign.json"),
    (["report", "{c}", "--force", "--out"], "summary.json", "summary.json"),
    (["report", "{c}", "--force", "--out"], "episodes/r.html", "episodes"),
    (["compare", "a={c}:random", "b={c}:sunny", "--force", "--json"], "campaign.json", "campaign.json"),
    (["compare", "a={c}:random", "b={c}:sunny", "--force", "--json"], "episodes.csv", "episodes.csv"),
    (["reactivity", "--campaign", "{c}", "--policy", "random", "--force", "--quiet", "--out"], "campaign.json",
     "campaign.json"),
])
def test_an_output_onto_its_own_campaign_is_refused_and_the_campaign_kept(camp, capsys, argv, out, onto) -> None:
    before = _files(camp)
    flag = argv[-1]
    assert main([a.format(c=camp) for a in argv] + [str(camp / out)]) == 2
    err = capsys.readouterr().err
    assert f"{flag} '{camp / out}' lies inside this command's input '{camp}' (onto its '{onto}')" in err
    assert _files(camp) == before  # not one byte changed: the campaign is still readable
    assert main(["report", str(camp), "--markdown"]) == 0


def test_an_output_that_is_the_input_or_a_link_to_it_is_refused(camp, tmp_path, capsys) -> None:
    before = _files(camp)
    link = tmp_path / "figures.json"
    link.symlink_to(camp / "campaign.json")  # resolved: the link leads onto the campaign's description
    assert main(["compare", f"a={camp}:random", f"b={camp}:sunny", "--json", str(link), "--force"]) == 2
    assert f"--json '{link}' lies inside this command's input '{camp}' (onto its 'campaign.json')" in \
        capsys.readouterr().err
    assert main(["report", str(camp), "--out", str(camp), "--force"]) == 2
    assert f"--out '{camp}' is this command's input '{camp}'" in capsys.readouterr().err
    config = tmp_path / "c.toml"
    config.write_text(TINY_RUN)
    assert main(["corners", "--config", str(config), "--scenes", "1", "--out", str(config), "--force",
                 "--quiet"]) == 2
    assert f"--out '{config}' is this command's input '{config}'" in capsys.readouterr().err
    hard = tmp_path / "hard.html"
    os.link(camp / "campaign.json", hard)  # another name for the campaign's own file
    assert main(["report", str(camp), "--out", str(hard), "--force"]) == 2
    assert f"--out '{hard}' is a hard link to '{camp / 'campaign.json'}'" in capsys.readouterr().err
    assert config.read_text() == TINY_RUN and _files(camp) == before and link.is_symlink()
    # report's own CAMPAIGN/report.html lies inside its input, but beside what it reads, never onto it
    # report writes these; summary.json names the campaign's folder; the manifest lists report.html
    kept = ("report", "summary.json", ".genesis-rl.manifest.json")
    assert main(["report", str(camp), "--force"]) == 0
    assert (camp / "report.html").read_text().startswith("<!doctype html>")
    assert {k: v for k, v in _files(camp).items() if not k.startswith(kept)} == \
        {k: v for k, v in before.items() if not k.startswith(kept)}
    capsys.readouterr()


# --- standard output, FIFOs, links, devices --------------------------------------------------------------------

@pytest.mark.parametrize("name", ["-", "/dev/stdout"])
def test_json_to_standard_output(camp, tmp_path, capsys, monkeypatch, name) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["compare", f"a={camp}:random", f"b={camp}:sunny", "--json", name]) == 0
    out, err = capsys.readouterr()
    figures = json.loads(out)  # standard output holds the JSON alone; the Markdown table went to stderr
    assert figures["policies"]["a"]["episodes"] == 1 and figures["policies"]["b"]["episodes"] == 1
    assert "| " in err
    assert main(["scenes", "--count", "2", "--out", name, "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert len(json.loads(out)["scenes"]) == 2 and json.loads(err)["out"] == name
    assert sorted(os.listdir(tmp_path)) == ["camp"]  # no file named '-' and nothing else written
    assert main(["report", str(camp), "--out", name]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("<!doctype html>") and err.strip() == f"report: {name}"


def test_a_folder_output_refuses_standard_output(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["drive", "--out", "-", "--steps", "2", "--system", "blind", "--no-gif", "--quiet"]) == 2
    assert "--out '-': this command writes a folder of files" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


def test_a_fifo_is_written_in_place(tmp_path, capsys) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()), daemon=True)
    reader.start()
    code = main(["scenes", "--count", "2", "--out", str(fifo), "--quiet"])  # no --force: nothing is replaced
    if not got and fifo.is_fifo():  # nothing written: release the reader
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    reader.join(timeout=30)
    assert code == 0
    assert len(json.loads(got[0])["scenes"]) == 2
    assert fifo.is_fifo() and sorted(os.listdir(tmp_path)) == ["pipe"]
    capsys.readouterr()


def test_a_fifo_nobody_reads_is_refused_instead_of_hanging(tmp_path, capsys, monkeypatch) -> None:
    from genesis_rl.core.files import output_paths

    monkeypatch.setattr(output_paths, "FIFO_READER_WAIT_S", 0.3)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    assert main(["scenes", "--count", "1", "--out", str(fifo), "--quiet"]) == 2
    assert time.monotonic() - t0 < 20  # a plain open() waited here for ever
    assert "is a FIFO that no process read within 0.3 s" in capsys.readouterr().err
    assert fifo.is_fifo() and os.listdir(tmp_path) == ["pipe"]


def test_a_link_or_a_device_is_never_replaced(tmp_path, capsys) -> None:
    link = tmp_path / "c.json"
    link.symlink_to("target.json")
    assert main(["scenes", "--count", "1", "--out", str(link), "--force", "--quiet"]) == 2
    assert f"output '{link}' is a symbolic link to 'target.json'; genesis-rl neither replaces a link" \
        in capsys.readouterr().err
    assert link.is_symlink() and os.readlink(link) == "target.json" and not (tmp_path / "target.json").exists()
    sock_path = tmp_path / "s"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(sock_path))
    try:
        assert main(["map", "export", "--out", str(sock_path), "--force"]) == 2
        assert f"output '{sock_path}' is a socket, not a regular file; refusing to replace it" in \
            capsys.readouterr().err
        assert sock_path.is_socket()
        # the atomic write itself refuses too (a link put there while a command ran)
        with pytest.raises(UserInputError, match="is a symbolic link"):
            io_utils.atomic_write_text(link, "x")
        assert link.is_symlink() and sorted(os.listdir(tmp_path)) == ["c.json", "s"]
    finally:
        sock.close()
    assert main(["scenes", "--count", "1", "--out", "/dev/null", "--quiet"]) == 0  # written through, discarded
    assert Path("/dev/null").is_char_device()
    capsys.readouterr()


# --- --force replaces only what genesis-rl wrote ------------------------------------------------------------

def _run_folder(path: Path) -> Path:
    """A run folder as training leaves it: written under the folder's hold, which lists it in the manifest."""
    path.mkdir()
    with output_folder.hold(path):
        output_folder.write_marker(path, "run")
        (path / "config.toml").write_text(TINY_RUN)
        (path / "checkpoints").mkdir()
        (path / "checkpoints" / "last.json").write_text('{"timesteps": 16}')
    return path


def test_train_force_keeps_and_names_what_it_did_not_write(tmp_path, capsys) -> None:
    run = _run_folder(tmp_path / "run")
    (run / "notes.txt").write_text("what I tried")
    (run / "eval").mkdir()  # a campaign kept beside the run (evaluate's default --out)
    (run / "eval" / "campaign.json").write_text('{"schema": "genesis-rl/campaign"}')
    config = tmp_path / "c.toml"
    config.write_text(TINY_RUN)
    before = _files(run)
    assert main(["train", "--config", str(config), "--out", str(run), "--force", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"--force: run folder '{run}' also holds what genesis-rl did not write there: eval/, notes.txt" in err
    assert _files(run) == before


def test_evaluate_force_keeps_a_users_file_in_a_campaign(campaign, camp, capsys) -> None:
    (camp / "notes.txt").write_text("the scene 3 collision looks wrong")
    before = _files(camp)
    assert main(["evaluate", "--catalog", str(campaign.parent / "cat.json"), "--policies", "random", "--scenes", "1",
                 "--steps", "5", "--system", "blind", "--out", str(camp), "--force", "--quiet"]) == 2
    assert f"campaign folder '{camp}' also holds what genesis-rl did not write there: notes.txt" in \
        capsys.readouterr().err
    assert _files(camp) == before


def test_replace_removes_only_the_tools_own_entries(tmp_path) -> None:
    run = _run_folder(tmp_path / "run")
    with output_folder.hold(run):  # written by the tool: listed in the manifest as the hold ends
        (run / "tb").mkdir()
        (run / "tb" / "progress.csv").write_text("x")
        (run / ".agent.zip.ab12cd34.zip").write_text("a temporary of a killed write")
    output_folder.check_target(run, "run", force=True)  # all its own: replaceable
    (run / "mine.txt").write_text("keep")
    output_folder.replace(run, "run")  # one that appeared after the check is kept all the same
    assert sorted(p.name for p in run.iterdir()) == [".genesis-rl.json", "mine.txt"]
