"""Hostile inputs and a hostile machine (issue 21, items 6 and 8, and the sweep's findings): operating-system
errors are one line naming the path and the cause with exit status 2 and no half-written file; ``report``
writes elsewhere when its campaign folder is read-only; damaged numbers never reach ``summary.json``; a GPU
asked for and missing is refused. ``tests/hostile/sweep_commands.py`` runs the full sweep (docs/reliability.md)."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import io_utils

REPO = Path(__file__).resolve().parents[1]


def _raiser(err: BaseException):  # noqa: ANN202
    def fail(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise err
    return fail


@pytest.mark.parametrize(("code", "cause"), [
    (errno.EACCES, "Permission denied (EACCES)"),
    (errno.EROFS, "Read-only file system (EROFS)"),
    (errno.ENOSPC, "No space left on device (ENOSPC)"),
    (errno.EPERM, "Operation not permitted (EPERM)"),
])
def test_an_os_error_while_writing_is_one_line_naming_the_output(tmp_path, capsys, monkeypatch, code, cause) -> None:
    # the error as the OS raises it inside a write: about the temporary file, or (disk full) about no file at all
    monkeypatch.setattr(io_utils.os, "replace", _raiser(OSError(code, os.strerror(code))))
    out = tmp_path / "cat.json"
    assert main(["scenes", "--count", "1", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert err.startswith(f"genesis-rl scenes: error: '{out}': {cause}; ")
    assert os.listdir(tmp_path) == []  # no temporary file left behind


def test_a_name_too_long_is_one_line(tmp_path, capsys) -> None:
    out = tmp_path / ("x" * 300 + ".json")
    assert main(["scenes", "--count", "1", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "File name too long (ENAMETOOLONG); shorten the path" in err
    assert os.listdir(tmp_path) == []


def test_a_writer_failing_on_a_full_disk_is_named_as_a_full_disk(tmp_path, monkeypatch) -> None:
    """torch reports a failed write as a RuntimeError; on a full disk it becomes ENOSPC naming the file."""
    monkeypatch.setattr(io_utils, "_disk_full", lambda folder: True)
    with pytest.raises(OSError, match="No space left on device") as caught:
        io_utils.atomic_write(tmp_path / "w.pt", _raiser(RuntimeError("PytorchStreamWriter failed writing file")))
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(tmp_path / "w.pt")
    monkeypatch.setattr(io_utils, "_disk_full", lambda folder: False)
    with pytest.raises(RuntimeError):  # not the disk: a bug stays a bug, with its traceback
        io_utils.atomic_write(tmp_path / "w.pt", _raiser(RuntimeError("a bug")))
    # pyarrow's wording: "[errno 28]" in the message of an OSError without errno
    with pytest.raises(OSError) as caught:
        io_utils.atomic_write(tmp_path / "t.parquet", _raiser(OSError("Error writing. Detail: [errno 28] No space")))
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(tmp_path / "t.parquet")
    assert os.listdir(tmp_path) == []


def test_a_dangling_symlink_is_not_overwritten_without_force(tmp_path, capsys) -> None:
    link = tmp_path / "c.json"
    link.symlink_to("elsewhere/c.json")
    assert main(["scenes", "--count", "1", "--out", str(link), "--quiet"]) == 2
    assert "already exists; pass --force" in capsys.readouterr().err
    assert link.is_symlink() and os.readlink(link) == "elsewhere/c.json"


def test_cuda_asked_for_without_a_gpu_is_refused(tmp_path, capsys, monkeypatch) -> None:
    import torch

    from genesis_rl.training.config import PPOConfig

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(UserInputError, match=r"ppo.device = 'cuda:1' but torch.cuda.is_available\(\) = False"):
        PPOConfig(device="cuda:1").check_device_present()
    PPOConfig(device="auto").check_device_present()
    PPOConfig(device="cpu").check_device_present()
    config = tmp_path / "c.toml"
    config.write_text("[ppo]\ndevice = 'cuda'\nn_steps = 8\n[train]\ntotal_timesteps = 16\n[env]\nscenes = 2\n")
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert 'torch.cuda.is_available() = False' in capsys.readouterr().err
    assert not (tmp_path / "run").exists()  # a refused new run leaves no folder


# -- a campaign, read-only and damaged -------------------------------------------------------------
@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("camp")
    assert main(["scenes", "--count", "2", "--out", str(folder / "cat.json"), "--quiet"]) == 0
    assert main(["evaluate", "--catalog", str(folder / "cat.json"), "--policies", "random", "--scenes", "1",
                 "--steps", "5", "--system", "blind", "--out", str(folder / "camp"), "--quiet", "--no-report"]) == 0
    return folder / "camp"


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_report_leaves_unchanged_summary_files_alone(campaign, tmp_path, capsys) -> None:
    camp = tmp_path / "camp"
    shutil.copytree(campaign, camp)
    (camp / "episodes.csv").write_text("stale\n")  # a summary file that differs is brought up to date
    assert main(["report", str(camp), "--out", str(tmp_path / "r.html")]) == 0
    assert (camp / "episodes.csv").read_bytes() == (campaign / "episodes.csv").read_bytes()
    assert json.loads((camp / "summary.json").read_text())["campaign"] == str(camp)  # it names its folder
    for name in ("summary.json", "episodes.csv"):
        os.utime(camp / name, (1, 1))
    assert main(["report", str(camp), "--out", str(tmp_path / "r2.html")]) == 0
    assert all((camp / name).stat().st_mtime == 1 for name in ("summary.json", "episodes.csv"))


def test_report_of_a_campaign_it_cannot_write_goes_to_out(campaign, tmp_path, capsys, monkeypatch) -> None:
    camp = tmp_path / "camp"
    shutil.copytree(campaign, camp)
    (camp / "episodes.csv").write_text("stale\n")  # so that report would update it
    before = _files(camp)
    real = io_utils.atomic_write

    def read_only(path, writer):  # noqa: ANN001, ANN202 - the campaign folder is read-only
        if Path(path).parent == camp:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real(path, writer)

    monkeypatch.setattr(io_utils, "atomic_write", read_only)
    assert main(["report", str(camp), "--out", str(tmp_path / "elsewhere" / "r.html")]) == 0
    captured = capsys.readouterr()
    assert "note: summary.json and episodes.csv of" in captured.err and "Read-only file system" in captured.err
    assert (tmp_path / "elsewhere" / "r.html").stat().st_size > 10_000
    assert _files(camp) == before
    assert main(["report", str(camp), "--force"]) == 2  # into the campaign folder: says where else to write
    assert "Read-only file system (EROFS); pass --out FILE to write the report elsewhere" in capsys.readouterr().err


def _mount_works(tmp_path: Path) -> bool:
    probe = tmp_path / "probe"
    probe.mkdir()
    try:
        r = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {probe}"],
                           capture_output=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return False
    finally:
        probe.rmdir()
    return r.returncode == 0


def test_report_on_a_read_only_mount(campaign, tmp_path) -> None:
    """The real thing, where a private mount namespace is allowed (root, or CI with user namespaces)."""
    if not _mount_works(tmp_path):
        pytest.skip("cannot mount in a private namespace here (needs root or user namespaces)")
    camp = tmp_path / "camp"
    shutil.copytree(campaign, camp)
    (camp / "summary.json").write_text("{}")  # differs from what report computes, so it would be rewritten
    before = _files(camp)
    py = f"PYTHONPATH={REPO} {sys.executable} -m genesis_rl"
    script = (f"mount --bind {camp} {camp} && mount -o remount,bind,ro {camp} && "
              f"{py} report {camp} --out {tmp_path / 'r.html'}")
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"not updated ('{camp}/summary.json': Read-only file system (EROFS))" in r.stderr
    assert (tmp_path / "r.html").is_file() and _files(camp) == before


def test_a_full_disk_is_one_line_and_leaves_nothing(tmp_path) -> None:
    if not _mount_works(tmp_path):
        pytest.skip("cannot mount in a private namespace here (needs root or user namespaces)")
    full = tmp_path / "full"
    full.mkdir()
    script = (f"mount -t tmpfs -o size=256k tmpfs {full} && (dd if=/dev/zero of={full}/filler bs=4k || true) "
              f"2>/dev/null && PYTHONPATH={REPO} {sys.executable} -m genesis_rl scenes --count 2 --out "
              f"{full}/c.json --quiet; echo rc=$?; ls -a {full}")
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=120)
    assert "rc=2" in r.stdout and "Traceback" not in r.stderr
    assert f"'{full}/c.json': No space left on device (ENOSPC)" in r.stderr
    assert r.stdout.split()[-3:] == [".", "..", "filler"]  # no temporary file left behind


@pytest.mark.parametrize(("field", "text"), [("total", "NaN"), ("mean_iou", "NaN"), ("return", "-Infinity"),
                                             ("min_gap", "NaN"), ("collision_speed", "Infinity")])
def test_report_refuses_an_episode_file_holding_nan(campaign, tmp_path, capsys, field, text) -> None:
    camp = tmp_path / "camp"
    shutil.copytree(campaign, camp)
    episode = sorted((camp / "episodes" / "random").glob("scene_*.json"))[0]
    row = json.loads(episode.read_text())
    episode.write_text(json.dumps({**row, field: 0.5}).replace(f'"{field}": 0.5', f'"{field}": {text}'))
    before = _files(camp)
    assert main(["report", str(camp), "--force"]) == 2
    err = capsys.readouterr().err
    assert f"'{episode}' is damaged: field '{field}' = {float(text)!r}" in err
    assert _files(camp) == before  # summary.json, episodes.csv and report.html as they were
    assert main(["report", str(camp), "--markdown"]) == 2


@pytest.mark.parametrize(("argv", "message"), [
    (["export", "{camp}", "--format", "xml"], "--format 'xml' is unknown; allowed: yolo, coco"),
    (["export", "{tmp}/nothere"], "campaign folder '{tmp}/nothere' does not exist"),
    (["report", "{tmp}/nothere"], "campaign folder '{tmp}/nothere' does not exist"),
    (["export", "{tmp}/afile"], "'{tmp}/afile' is a file; expected a campaign folder"),
    (["report", "{tmp}"], "'{tmp}' is not a campaign folder (no campaign.json); run genesis-rl evaluate first"),
])
def test_export_and_report_errors_say_what_happened(campaign, tmp_path, capsys, argv, message) -> None:
    (tmp_path / "afile").write_text("x")
    fill = {"camp": str(campaign), "tmp": str(tmp_path)}
    argv = [a.format(**fill) for a in argv] + (["--out", str(tmp_path / "ex")] if argv[0] == "export" else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message.format(**fill) in err and "damaged" not in err
    assert not (tmp_path / "ex").exists() and not (tmp_path / ".ex.partial").exists()


def test_a_failed_export_leaves_no_partial_folder(campaign, tmp_path, capsys, monkeypatch) -> None:
    from genesis_rl.exports import dataset as export

    frame = tmp_path / "f.jpg"
    frame.write_bytes(b"\xff\xd8\xff")  # a damaged frame: the export fails half-way
    monkeypatch.setattr(export, "_frames", lambda folder: [("random", 0, 1, frame)])
    monkeypatch.setattr(export, "read_steps", lambda path, columns=None, steps=None: [{"step": 1, "gt_boxes": []}])
    rows = export.load_campaign(campaign)[1]
    scene = rows["random"][0]["scene"]
    monkeypatch.setattr(export, "_frames", lambda folder: [("random", scene, 1, frame)])
    assert main(["export", str(campaign), "--out", str(tmp_path / "ex")]) == 2
    assert f"frame '{frame}' is damaged" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["f.jpg"]  # neither ex/, .ex.partial/ nor a lock file


# -- found by the sweep --------------------------------------------------------------------------------
def test_a_full_disk_while_locking_is_named_and_leaves_no_lock_file(tmp_path, monkeypatch) -> None:
    from genesis_rl.core.files import output_folder

    monkeypatch.setattr(output_folder.os, "pwrite", _raiser(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))))
    with pytest.raises(UserInputError, match=r"cannot lock output folder '.*out': '.*\.out\.genesis-rl\.lock': No "
                                             r"space left on device \(ENOSPC\)"):
        with output_folder.hold(tmp_path / "out"):
            pass
    assert os.listdir(tmp_path) == []


def test_a_folder_that_cannot_be_removed_is_named_in_full(tmp_path, monkeypatch) -> None:
    (tmp_path / "ex" / "images").mkdir(parents=True)
    (tmp_path / "ex" / "images" / "a.jpg").write_text("x")
    monkeypatch.setattr(os, "unlink", _raiser(OSError(errno.EROFS, os.strerror(errno.EROFS), "a.jpg")))
    with pytest.raises(OSError) as caught:
        io_utils.remove_tree(tmp_path / "ex")
    assert caught.value.filename == str(tmp_path / "ex" / "images" / "a.jpg")  # rmtree's own: 'a.jpg'


def test_train_resume_names_a_damaged_episode_log(tmp_path) -> None:
    from genesis_rl.training.checkpoint import truncate_csv

    log = tmp_path / "episodes.csv"
    log.write_bytes(bytes(range(256)))
    with pytest.raises(UserInputError, match=r"the episode log '.*episodes\.csv' is damaged"):
        truncate_csv(log, 3)


def test_evaluate_steps_that_would_run_for_days_are_refused(tmp_path, capsys) -> None:
    assert main(["evaluate", "--policies", "sunny", "--steps", "999999999", "--out", str(tmp_path / "c")]) == 2
    assert "--steps = 999,999,999, over the limit of 100,000 simulation steps" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


def test_a_folder_as_schedule_is_called_a_folder(tmp_path) -> None:
    from genesis_rl.world.knobs import parse_weather
    from genesis_rl.world.weather_schedule import load_schedule

    with pytest.raises(UserInputError, match="schedule '.*' is a folder; expected a CSV file"):
        load_schedule(tmp_path, parse_weather("clear_noon"), 5)


@pytest.mark.parametrize(("argv", "message"), [  # --frames 0 was a ZeroDivisionError
    (["bench", "sim", "--steps", "10", "--frames", "0"], "--frames = 0; allowed: an integer >= 1"),
    (["bench", "train", "--steps", "1"], "--steps = 1 must be >= 2"),  # was SB3's AssertionError
    (["bench", "sim", "--steps", "-1"], "--steps = -1 must be >= 1"),  # was accepted
    (["bench", "train", "--executors", "slurm"], "--executors 'slurm': bench train takes one of local, ray"),
    (["bench", "train", "--envs", "3"], "--steps = 2048 must be a multiple of --envs = 3"),
    (["bench", "train", "--updates", "0"], "--updates = 0 in 1..100"),
])
def test_bench_refuses_counts_it_cannot_time(capsys, argv, message) -> None:
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_a_recorded_weather_holding_nan_is_refused() -> None:
    from genesis_rl.world.knobs import Weather

    with pytest.raises(UserInputError, match=r"non-finite knob value\(s\) \{'fog_density': nan\}"):
        Weather.from_recorded({"fog_density": float("nan")})  # replay of a damaged record exited 0
