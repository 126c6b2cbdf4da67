"""The hostile-input sweep's own oracle (tests/hostile/sweep_files.py, issue 38): a sweep that called a crash a pass
would hide every failure it exists to find, so each outcome is shown on a command known to produce it."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import pytest

SCRIPT = Path(__file__).resolve().parent / "hostile" / "sweep_files.py"


@pytest.fixture(scope="module")
def sweep() -> ModuleType:
    spec = importlib.util.spec_from_file_location("hostile_sweep", SCRIPT)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules["hostile_sweep"] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    module.build_cases()
    return module


def _raw(sweep: ModuleType, tmp_path: Path, code: str, **kw: object) -> dict:
    """One case whose command is ``python -c code``, run in its own folder like every sweep case."""
    c = sweep.Case("t-" + str(abs(hash(code)) % 10**8), 4, "synthetic", [], raw=[sys.executable, "-c", code], **kw)
    return sweep.run_case(c, tmp_path, tmp_path / "no-fixtures", {})


@pytest.mark.parametrize("code, outcome", [
    ("import sys; print('genesis-rl x: error: --y must be >= 1', file=sys.stderr); sys.exit(2)", "pass"),
    ("raise SystemExit(134)", "abort"),
    ("import os; os.abort()", "abort"),
    ("import os, signal; os.kill(os.getpid(), signal.SIGSEGV)", "abort"),
    ("import sys; sys.setrecursionlimit(50)\ndef f(): f()\nf()", "traceback"),
    ("import sys; sys.exit(0)", "wrong-exit"),  # the case expects a refusal (exit 2)
    ("import sys; sys.exit(2)", "wrong-exit"),  # a refusal that says nothing
    ("import time; time.sleep(30)", "timeout"),
])
def test_oracle_classifies_synthetic_commands(sweep: ModuleType, tmp_path: Path, code: str, outcome: str) -> None:
    row = _raw(sweep, tmp_path, code, timeout=2.0)
    assert row["outcome"] == outcome, row
    if outcome == "timeout":
        assert row["seconds"] < 10  # the process group was killed, not waited for


def test_a_refusal_must_name_the_field(sweep: ModuleType, tmp_path: Path) -> None:
    """A swept field refused for another reason (a campaign blaming its own output file) is not a clean refusal."""
    blames = "import sys; print('x: error: episode.json is damaged', file=sys.stderr); sys.exit(2)"
    assert _raw(sweep, tmp_path / "a", blames, names=("decel",))["outcome"] == "wrong-exit"
    names = "import sys; print('x: error: rules.toml: decel = 1e-320 must be >= 0.1', file=sys.stderr); sys.exit(2)"
    assert _raw(sweep, tmp_path / "b", names, names=("decel",))["outcome"] == "pass"


def test_oracle_sees_data_loss_and_code_execution(sweep: ModuleType, tmp_path: Path) -> None:
    def setup(d: Path, fx: Path) -> None:
        (d / "input.json").write_text("{}")
        (d / "link").symlink_to("input.json")

    lost = _raw(sweep, tmp_path / "a", "import os; os.replace('input.json', 'link'); raise SystemExit(2)",
                setup=setup)
    assert lost["outcome"] == "data-loss" and "input.json" in lost["detail"] and "link" in lost["detail"]
    refuse = "import sys; print('x: error: no', file=sys.stderr); raise SystemExit(2)"
    allowed = _raw(sweep, tmp_path / "b", "open('input.json', 'w').write('[]')\n" + refuse, setup=setup,
                   may_change=("input.json",))
    assert allowed["outcome"] == "pass", allowed
    pwned = _raw(sweep, tmp_path / "c", f"open({sweep.MARKER!r}, 'w'); raise SystemExit(2)")
    assert pwned["outcome"] == "code-exec"
    # the payload the family-2 cases plant really does create the marker when unpickled
    import pickle

    (tmp_path / "d").mkdir()
    pickle.loads(sweep.payload(tmp_path / "d"))
    assert (tmp_path / "d" / sweep.MARKER).exists()


def test_cases_cover_six_families_with_enough_new_ones(sweep: ModuleType) -> None:
    core = [c for c in sweep.CASES if c.core]
    assert {c.family for c in core} == set(range(1, 7))
    assert sum(1 for c in core if not c.from_issue) >= 220
    assert len({c.id for c in sweep.CASES}) == len(sweep.CASES)
    assert all(c.expect for c in sweep.CASES)


def test_sweep_runs_real_cases_and_writes_its_reports(sweep: ModuleType, tmp_path: Path) -> None:
    """Two fixture-free cases through the command line end to end: both are refused cleanly today."""
    out, md = tmp_path / "s.json", tmp_path / "s.md"
    sweep.main(["--ids", "f5-scenes-count,f6-bench-workers-bad", "--out", str(out), "--markdown", str(md),
                "--work", str(tmp_path / "w")])
    report = json.loads(out.read_text())
    assert report["complete"] and report["cases"] == 2
    assert {r["id"]: r["outcome"] for r in report["results"]} == {"f5-scenes-count": "pass",
                                                                  "f6-bench-workers-bad": "pass"}
    assert all(r["exit"] == 2 and r["stderr"].startswith("genesis-rl") for r in report["results"])
    text = md.read_text()
    assert "| 5. no bound on work | 1 | 1 | 1 |" in text and "f6-bench-workers-bad" in text


def test_interrupt_cases_signal_at_the_moment_and_find_leftovers(sweep: ModuleType, tmp_path: Path) -> None:
    """SIGTERM once a file appears: ending by the signal is fine, a temporary left beside the output is not."""
    import signal

    clean = "import pathlib, time; pathlib.Path('go').touch(); time.sleep(30)"
    row = _raw(sweep, tmp_path / "a", clean, signal_when="go", signal_at=0.1, signal_num=signal.SIGTERM,
               expect=(0, 130, 143), timeout=20.0)
    assert row["outcome"] == "pass" and row["exit"] == -signal.SIGTERM and row["seconds"] < 15, row
    dirty = "import pathlib, time; pathlib.Path('.out.zip.k3j4h5g6.zip').touch(); time.sleep(30)"
    row = _raw(sweep, tmp_path / "b", dirty, signal_when=".out.zip.*", signal_at=0.1, signal_num=signal.SIGTERM,
               expect=(0, 130, 143), timeout=20.0)
    assert row["outcome"] == "wrong-exit" and ".out.zip.k3j4h5g6.zip" in row["detail"], row
