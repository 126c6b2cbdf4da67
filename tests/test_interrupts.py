"""Interrupts are clean (issue 38, build item 8): SIGINT or SIGTERM at a random moment of a training run or a
campaign, a checkpoint or an episode file being written included, ends the command with one line and status
130 or 143, leaves no temporary file and no lock, and ``--resume`` then ends exactly where an uninterrupted
run ends. The commands run as real processes (``python -m genesis_rl``), signalled from outside as a user or
a batch scheduler would, at seeded random moments of three kinds: start-up, training (or episodes), and the
instant a temporary file of an atomic write appears (a checkpoint's or an episode's)."""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from builders import tiny_run

import genesis_rl
from genesis_rl.commands.cli import main

#: tests/test_reliability.py's tiny run, longer (10 checkpoints): it is still training after five interruptions
TINY_RUN = tiny_run(train={"total_timesteps": 160})

ROOT = Path(genesis_rl.__file__).resolve().parents[1]  # the package under test, for the child processes


@pytest.fixture(autouse=True)
def _ctrl_c_delivered() -> object:
    """Ctrl-C as a terminal delivers it, whatever started the suite: a shell starts a background job (``cmd &``,
    ``nohup``) with SIGINT ignored, and a Python process that starts so keeps ignoring it, as do its children,
    so these tests failed in a suite started in the background while the code was right."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    before_term = signal.signal(signal.SIGTERM, signal.SIG_DFL)  # whatever a test before left (Ray's handler)
    yield
    signal.signal(signal.SIGINT, before)
    signal.signal(signal.SIGTERM, before_term)


def _default_sigint() -> None:
    """A child's SIGINT at its default, so that its interpreter installs KeyboardInterrupt (see above)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
MARKER = ".genesis-rl.json"


def _leftovers(top: Path) -> list[str]:
    """Hidden files under ``top`` other than the folders' markers: atomic writes' temporaries
    (``.NAME.XXXXXXXX.SUFFIX``, e.g. ``.step_00000016.zip.k2j4h1a_.zip``) and lock files
    (``.NAME.genesis-rl.lock``); the manifests of what was written are the tool's record, not leftovers."""
    return sorted(str(p.relative_to(top)) for p in top.rglob(".*")
                  if p.is_file() and p.name not in (MARKER, ".genesis-rl.manifest.json"))


def _temporary_appears(folder: Path, proc: subprocess.Popen, limit: float) -> bool:
    """Wait (polling every millisecond) until a temporary file of an atomic write exists under ``folder``."""
    end = time.monotonic() + limit
    while time.monotonic() < end and proc.poll() is None:
        if folder.is_dir() and any(p.name not in (MARKER, ".genesis-rl.manifest.json") for p in folder.rglob(".*")):
            return True
        time.sleep(0.001)
    return False


def _signalled(args: list[str], cwd: Path, signum: int, when: str, rng: random.Random, watch: Path,
               started: Callable[[], bool] = lambda: True, group: bool = False) -> dict:
    """Run ``genesis-rl ARGS`` in a child process and send it ``signum``: after a random delay from its start
    (``when`` = "start"), a random moment once ``started()`` is true ("run"), or the instant a temporary file
    appears under ``watch`` ("write"); with ``group``, to all its processes, as a terminal's Ctrl-C is.
    Returns its status, its stderr and the moment chosen."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "genesis_rl", *args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=group,
                            preexec_fn=_default_sigint)
    t0 = time.monotonic()
    if when == "start":
        time.sleep(rng.uniform(0.5, 4.0))  # not in the interpreter's own start-up (docs/reliability.md)
    elif when == "run":
        while not started() and proc.poll() is None and time.monotonic() - t0 < 120:
            time.sleep(0.01)
        time.sleep(rng.uniform(0.0, 0.6))
    else:
        _temporary_appears(watch, proc, 120)
        time.sleep(rng.uniform(0.0, 0.002))
    moment = round(time.monotonic() - t0, 3)
    sent = proc.poll() is None
    if sent:
        if group:
            os.killpg(proc.pid, signum)
        else:
            proc.send_signal(signum)
    out, err = proc.communicate(timeout=300)
    return {"status": proc.returncode, "stderr": err, "at": moment, "when": when, "sent": sent,
            "signal": signal.Signals(signum).name, "seconds": round(time.monotonic() - t0, 1), "stdout": out}


def _rewritten(path: Path) -> Callable[[], bool]:
    """Whether ``path`` has been written since now (a new checkpoint: the run is training)."""
    before = path.stat().st_mtime_ns if path.exists() else 0
    return lambda: path.exists() and path.stat().st_mtime_ns != before


def _episodes(camp: Path) -> int:
    return sum(1 for _ in camp.glob("episodes/*/*.json"))


def _check_outcome(trial: dict, top: Path) -> None:
    expected = {0, 128 + signal.Signals[trial["signal"]]}  # 0: the command ended before the signal came
    assert trial["status"] in expected, trial
    assert "Traceback" not in trial["stderr"], trial
    if trial["status"]:
        lines = trial["stderr"].strip().splitlines()
        assert lines and "interrupted" in lines[-1], trial
        # once the command line runs, one line and nothing else (while it imports, a library may have printed)
        assert len(lines) == 1 or not lines[-1].startswith("genesis-rl"), trial
    assert _leftovers(top) == [], trial


def _policy_and_optimizer(path: Path) -> dict:
    from stable_baselines3 import PPO

    model = PPO.load(path, device="cpu")
    return {"policy": model.policy.state_dict(), "optimizer": model.policy.optimizer.state_dict()}


def _same_tensors(a: object, b: object) -> bool:
    import torch

    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same_tensors(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same_tensors(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return torch.equal(a, b)
    return a == b


#: how many signals the training sweep sends (more for a longer sweep, e.g. the 40 of docs/reliability.md)
TRIALS = int(os.environ.get("GENESIS_RL_INTERRUPT_TRIALS", "5"))


def _finished_like(cut: Path, whole: Path) -> None:
    """``cut`` ended where the uninterrupted run ``whole`` did: the same episodes and weights, bit for bit."""
    assert json.loads((cut / "train_result.json").read_text())["timesteps"] == 160
    assert (cut / "episodes.csv").read_text() == (whole / "episodes.csv").read_text()
    assert _same_tensors(_policy_and_optimizer(cut / "agent.zip"), _policy_and_optimizer(whole / "agent.zip"))


@pytest.mark.render
@pytest.mark.slow
def test_signals_at_random_moments_of_training_leave_a_run_that_resumes_exactly(tmp_path, capsys) -> None:
    """Five signals (GENESIS_RL_INTERRUPT_TRIALS), SIGINT and SIGTERM in turn, each into the next process of
    one run (the first trains it, the others resume it): during start-up, during training, and as a
    checkpoint file is being written. Each ends with one line and 130/143 (or 0, when the run had ended), no
    temporary file and no lock; the run that --resume finishes has the uninterrupted run's episodes and
    weights, bit for bit (a run that ends is checked so, and the next signals go into a new one)."""
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_RUN)
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main(["train", "--config", str(config), "--out", str(whole), "--quiet"]) == 0
    capsys.readouterr()
    assert len((whole / "episodes.csv").read_text().splitlines()) == 1 + 16

    pointer = cut / "checkpoints" / "last.json"
    rng = random.Random(38)
    kinds = ["write", "run", "start", "write", "run"]
    trials, runs = [], 1
    for i in range(TRIALS):
        when, signum = kinds[i % len(kinds)], (signal.SIGINT, signal.SIGTERM)[i % 2]
        args = (["train", "--out", "cut", "--resume", "--quiet"] if cut.exists()
                else ["train", "--config", str(config), "--out", "cut", "--quiet"])
        trial = _signalled(args, tmp_path, signum, when, rng, cut / "checkpoints", _rewritten(pointer))
        trials.append(trial)
        _check_outcome(trial, tmp_path)
        if (cut / "train_result.json").is_file():  # this process finished the run: check it, start another
            _finished_like(cut, whole)
            shutil.rmtree(cut)
            runs += 1
        elif cut.exists():  # a run stopped before its first checkpoint is removed; otherwise it resumes
            last = json.loads(pointer.read_text())
            assert all((cut / "checkpoints" / last[k]).is_file() for k in ("checkpoint", "state"))
    with capsys.disabled():
        print(json.dumps({"runs": runs, "trials": [{k: t[k] for k in ("when", "signal", "at", "seconds", "status")}
                                                   for t in trials]}))
    assert sum(t["status"] != 0 for t in trials) >= 0.8 * TRIALS  # the signals did interrupt (not all too late)

    args = ["train", "--out", str(cut), "--resume", "--quiet"] if cut.exists() else \
        ["train", "--config", str(config), "--out", str(cut), "--quiet"]
    assert main(args) == 0
    capsys.readouterr()
    _finished_like(cut, whole)
    assert _leftovers(tmp_path) == []


@pytest.mark.render
def test_sigterm_while_a_checkpoint_is_written_waits_for_it(tmp_path) -> None:
    """The issue's reproduction: SIGTERM the instant a checkpoint's temporary file appears used to kill the
    process there, leaving ``.step_N.zip.XXXX.zip`` and the folder's lock behind (status -15). Now the
    checkpoint is finished, last.json names it, and the command exits 143 with one line naming --resume."""
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_RUN)
    trial = _signalled(["train", "--config", str(config), "--out", "cut", "--quiet"], tmp_path, signal.SIGTERM,
                       "write", random.Random(0), tmp_path / "cut" / "checkpoints")
    _check_outcome(trial, tmp_path)
    assert trial["status"] == 143
    assert "--resume continues from the checkpoint at step 16" in trial["stderr"]
    last = json.loads((tmp_path / "cut" / "checkpoints" / "last.json").read_text())
    assert last["timesteps"] == 16  # the checkpoint being written when the signal came, whole
    assert (tmp_path / "cut" / "checkpoints" / "step_00000016.zip").stat().st_size > 100_000


@pytest.mark.render
@pytest.mark.slow
def test_signals_during_a_campaign_leave_it_resumable_to_the_same_summary(tmp_path, capsys) -> None:
    """An evaluate campaign signalled as an episode file is being written, during its episodes, and (Ctrl-C
    to the process group, two pool workers) as a step file is being written: each ends with one line and
    130/143, no temporary file, no lock; --resume finishes it with the uninterrupted campaign's summary."""
    catalog = tmp_path / "highway.json"
    assert main(["scenes", "--map", "highway", "--count", "10", "--seed", "1", "--out", str(catalog),
                 "--quiet"]) == 0
    common = ["evaluate", "--policies", "random,sunny", "--catalog", str(catalog), "--scenes", "8", "--steps", "150",
              "--system", "blind", "--no-report", "--quiet"]
    assert main([*common, "--out", str(tmp_path / "whole")]) == 0
    capsys.readouterr()
    camp = tmp_path / "camp"
    whole_policies = json.loads((tmp_path / "whole" / "summary.json").read_text())["policies"]
    rng = random.Random(7)
    trials = []
    # the third: Ctrl-C in a terminal, which reaches the pool's worker processes too. An episode's temporary file
    # lives for well under a millisecond, so a poll can miss every one of them and the command end before its
    # signal (CI, stop 43): such a campaign is checked as finished and the next signals go into a new one, up to
    # six trials in all, until three signals have landed.
    kinds = [(signal.SIGTERM, "write", "episodes", 1), (signal.SIGINT, "run", "", 1),
             (signal.SIGINT, "write", "steps", 2)]
    for signum, when, watch, workers in (kinds * 2)[:6]:
        args = [*common, "--out", "camp", "--workers", str(workers),
                *(["--resume"] if (camp / "campaign.json").is_file() else [])]
        done = _episodes(camp)
        trial = _signalled(args, tmp_path, signum, when, rng, camp / watch, lambda n=done: _episodes(camp) > n,
                           group=workers > 1)
        trials.append(trial)
        _check_outcome(trial, tmp_path)
        if (camp / "summary.json").is_file():  # this process finished the campaign: check it, start another
            assert json.loads((camp / "summary.json").read_text())["policies"] == whole_policies
            shutil.rmtree(camp)
        if sum(t["status"] != 0 for t in trials) == 3:
            break
    with capsys.disabled():
        print(json.dumps([{k: t[k] for k in ("when", "signal", "at", "sent", "seconds", "status")} for t in trials]))
    assert sum(t["status"] != 0 for t in trials) >= 2  # the signals did interrupt (not all too late)
    assert main([*common, "--out", str(camp), *(["--resume"] if camp.exists() else [])]) == 0
    capsys.readouterr()
    summary = json.loads((camp / "summary.json").read_text())
    assert summary["policies"] == json.loads((tmp_path / "whole" / "summary.json").read_text())["policies"]
    assert _episodes(camp) == 16
    assert _leftovers(tmp_path) == []


# -- the mechanism, in this process -------------------------------------------------------------------------

def test_a_signal_during_a_deferred_write_arrives_after_it_and_a_second_one_at_once() -> None:
    """The first SIGTERM waits for the block's end (the write is whole); a second one during the block goes
    through at once, and a library's wrapping of it (torch's RuntimeError) comes out as Interrupted."""
    from genesis_rl.core.signals import Interrupted, deferred_signals, exit_status, interrupts_raise

    done = []
    with interrupts_raise():
        with pytest.raises(Interrupted) as caught:
            with deferred_signals():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.01)
                done.append("written")
        assert done == ["written"] and exit_status(caught.value) == 143

        with pytest.raises(Interrupted) as caught:
            with deferred_signals():
                os.kill(os.getpid(), signal.SIGINT)
                try:
                    os.kill(os.getpid(), signal.SIGINT)
                    time.sleep(0.01)
                except KeyboardInterrupt as err:  # as torch.save reports an interrupt inside its writer
                    raise RuntimeError("PytorchStreamWriter failed writing file") from err
                done.append("not reached")
        assert done == ["written"] and exit_status(caught.value) == 130
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # main() is called from tests and notebooks
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
