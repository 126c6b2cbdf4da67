"""Small refusals a hostile probe of 0.29.0 found: each once silently did something other than asked."""

from __future__ import annotations

import importlib
import sys

import pytest

from genesis_rl.commands.cli import main


@pytest.mark.parametrize("argv", [
    ["map", "export", "--map", "urban"],
    ["scenes", "--map", "urban", "--count", "1"],
])
def test_an_out_ending_in_a_slash_is_a_folder_not_a_file(tmp_path, capsys, argv) -> None:
    """``--out newdir/`` for a command that writes one file had written a regular file named ``newdir``."""
    out = str(tmp_path / "newdir") + "/"
    assert main([*argv, "--out", out]) == 2
    assert not (tmp_path / "newdir").exists()
    err = capsys.readouterr().err
    assert "--out" in err and "ends in '/'" in err and "give a file name" in err


def test_an_out_ending_in_a_slash_that_is_a_folder_is_refused_as_a_folder(tmp_path, capsys) -> None:
    (tmp_path / "there").mkdir()
    assert main(["map", "export", "--map", "urban", "--out", str(tmp_path / "there") + "/"]) == 2
    assert list((tmp_path / "there").iterdir()) == []


@pytest.mark.parametrize("extra", [["--trials", "0"], ["--members", "low_sun"], ["--search-budget", "3"]])
def test_benchmark_smoke_refuses_the_matrix_flags_it_would_ignore(tmp_path, capsys, extra) -> None:
    assert main(["benchmark", "--smoke", *extra, "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert extra[0] in err and "--smoke runs its own fixed matrix" in err
    assert not (tmp_path / "b").exists()


def test_importing_main_runs_nothing(monkeypatch) -> None:
    """A record naming ``genesis_rl.__main__:X`` had re-run the whole command line nested inside the first."""
    monkeypatch.setattr(sys, "argv", ["genesis-rl", "--version"])
    sys.modules.pop("genesis_rl.__main__", None)
    module = importlib.import_module("genesis_rl.__main__")  # would exit through SystemExit if it ran the CLI
    assert callable(module.main)


def test_bench_is_speed_under_its_old_name(capsys) -> None:
    assert main(["bench", "catalog", "--scenes", "2"]) == 0
    captured = capsys.readouterr()
    assert "'bench' is now 'genesis-rl speed'" in captured.err and '"scenes": 2' in captured.out
    assert main(["speed", "catalog", "--scenes", "2"]) == 0
    assert "is now" not in capsys.readouterr().err


def test_reactivity_never_writes_onto_the_agent_run_its_campaign_plays(v029, capsys) -> None:
    """``reactivity --out RUN/agent.zip --force`` had replaced the agent the campaign plays (exit 0)."""
    agent = (v029 / "run" / "agent.zip").read_bytes()
    for target in ("run/agent.zip", "run/config.toml", "run/catalog.json"):
        assert main(["reactivity", "--campaign", "camp", "--policy", "agent", "--out", target, "--force",
                     "--quiet"]) == 2
        assert "is this command's input" in capsys.readouterr().err
    assert (v029 / "run" / "agent.zip").read_bytes() == agent


def test_corners_never_writes_onto_the_weights_its_config_names(tmp_path, capsys) -> None:
    from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS

    weights = tmp_path / "w.pt"
    weights.write_bytes(DEFAULT_WEIGHTS.read_bytes())
    config = tmp_path / "c.toml"
    config.write_text(f'[env]\nsystem = "builtin"\nsystem_kwargs = {{ weights = "{weights}" }}\n')
    assert main(["corners", "--config", str(config), "--out", str(weights), "--force", "--scenes", "1"]) == 2
    assert "is this command's input" in capsys.readouterr().err
    assert weights.read_bytes() == DEFAULT_WEIGHTS.read_bytes()


@pytest.mark.parametrize(("module", "allowed"), [
    ("genesis_rl.__main__", False), ("genesis_rl.commands.cli", False), ("genesis_rl.benchmark.matrix", False),
    ("genesis_rl.sut.system.builtin", True), ("genesis_rl.system.builtin", True), ("genesis_rl.loop.rules", True),
    ("genesis_rl.adversaries.search", True), ("genesis_rl.world.knobs", True), ("evil", False)])
def test_the_import_gate_admits_the_plugin_layers_only(module: str, allowed: bool) -> None:
    from genesis_rl.core.plugins import gate, import_allowed

    with gate([]):
        assert import_allowed(module) is allowed


def test_a_record_naming_the_command_line_is_refused_at_the_gate(v029, tmp_path, capsys) -> None:
    import json

    record = v029 / "camp" / "records" / "agent_scene_0001.json"
    rec = json.loads(record.read_text())
    rec["system"]["spec"] = "genesis_rl.__main__:Sys"
    record.write_text(json.dumps(rec))
    assert main(["replay", str(record), "--out", str(tmp_path / "r"), "--quiet", "--no-gif"]) == 2
    assert "genesis_rl.__main__" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["scenes", "--help"]])
def test_help_and_version_to_a_full_device_say_so(argv) -> None:
    """argparse swallows the write error: ``--help > /dev/full`` had exited 0 with nothing written."""
    import os
    import subprocess

    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    with open("/dev/full", "w") as full:
        r = subprocess.run([sys.executable, "-m", "genesis_rl", *argv], stdout=full, stderr=subprocess.PIPE,
                           text=True, timeout=60)
    assert r.returncode == 2 and "could not be written" in r.stderr


def test_a_benchmark_stopped_in_its_first_trial_names_resume(tmp_path, monkeypatch) -> None:
    """After SIGTERM before a trial's first episode the trial's own hint ("run the command again") had reached
    the user, and the same command was then refused: the benchmark folder stays, only --resume continues."""
    from genesis_rl.benchmark import matrix
    from genesis_rl.core.signals import resume_hint, set_resume_hint

    def stopped(*args, **kwargs):
        err = KeyboardInterrupt()
        set_resume_hint(err, "no episode had finished, so 'x' was removed; run the command again")
        raise err

    monkeypatch.setattr(matrix, "run_campaign_once", stopped)
    spec = matrix.BenchmarkSpec(members=("low_sun",), policies=("sunny",), trials=1, scenes=1, steps=5)
    with pytest.raises(KeyboardInterrupt) as caught:
        matrix.run_benchmark(spec, tmp_path / "b", progress=False)
    assert "--resume runs the rest" in resume_hint(caught.value)
    assert (tmp_path / "b" / "benchmark.json").exists()


@pytest.mark.parametrize(("argv", "message"), [
    (["scenes", "--count", "0"], "genesis-rl scenes: error: --count = 0; allowed: an integer >= 1"),
    (["zoo", "truth", "stall_braking", "--held-out", "0"], "genesis-rl zoo: error: --held-out = 0; allowed:"),
    (["bench", "system", "--frames", "-3"], "genesis-rl bench: error: --frames = -3; allowed: an integer >= 1"),
    (["harden", "CAMP", "--rounds", "1000"], "genesis-rl harden: error: --rounds = 1,000, over the limit of 100"),
    (["estimate", "--member", "low_sun", "--workers", "0"], "genesis-rl estimate: error: --workers = 0; allowed"),
])
def test_a_count_flag_out_of_bounds_is_refused_as_it_is_parsed(tmp_path, capsys, argv, message) -> None:
    """Count flags declare their bounds where they are defined (cli_args.count): refused before the command runs,
    naming the command, the flag and what is allowed, exit 2, nothing written."""
    out = tmp_path / "out.json"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1
    assert not out.exists()


def test_a_count_limit_is_raised_by_its_variable_at_parse_time(monkeypatch, capsys) -> None:
    import argparse

    from genesis_rl.commands.cli_args import count
    from genesis_rl.core import limits
    from genesis_rl.core.errors import UserInputError

    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, action=count(1, limits.SIM_STEPS), default=5)
    assert parser.parse_args([]).steps == 5
    with pytest.raises(UserInputError, match="--steps = 200,000, over the limit of 100,000"):
        parser.parse_args(["--steps", "200000"])
    monkeypatch.setenv("GENESIS_RL_MAX_SIM_STEPS", "300000")
    assert parser.parse_args(["--steps", "200000"]).steps == 200_000
