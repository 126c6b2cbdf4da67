"""Issue 38, items 5 to 7: depth and size limits on every parsed file, budgets bounded, the Ray address checked
in seconds, and CARLA connection errors classified. Each hostile input is one line on stderr with exit status 2
(never a RecursionError, a _csv.Error, an abort or a run that would take years), and answers at once.

The network tests run tiny servers on 127.0.0.1 only: one that answers like an HTTP server, one that accepts
and never answers, a closed port, a fake gRPC server and a fake CARLA (msgpack-rpc) server."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.carla.connection import check_numbers

REPO = Path(__file__).resolve().parents[1]


def _one_line_error(capsys, command: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and err.count("\n") == 0, err
    assert err.startswith(f"genesis-rl {command}: error: "), err
    return err


def _deep_json(n: int) -> str:
    return '{"schema": "genesis-rl/scene-catalog", "version": 1, "scenes": ' + "[" * n + "]" * n + "}"


# -- item 5: depth and size limits on parsed files ------------------------------------------------------------
def test_a_200000_deep_json_catalog_is_one_line_exit_2(tmp_path, capsys) -> None:
    """json.loads gives up at about 1,000 levels with a RecursionError; the depth is measured first."""
    catalog = tmp_path / "deep.json"
    catalog.write_text(_deep_json(200_000))
    t0 = time.monotonic()
    assert main(["drive", "--catalog", str(catalog), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert time.monotonic() - t0 < 10
    err = _one_line_error(capsys, "drive")
    assert f"catalog file '{catalog}' is nested 200,001 levels deep, over the limit of 64 levels" in err
    assert "GENESIS_RL_MAX_NESTING" in err
    assert not (tmp_path / "out").exists()


def test_deep_records_and_campaign_files_are_one_line(tmp_path, capsys) -> None:
    record = tmp_path / "rec.json"
    record.write_text("[" * 100_000 + "]" * 100_000)
    assert main(["replay", str(record), "--out", str(tmp_path / "r")]) == 2
    assert f"record '{record}' is nested 100,000 levels deep" in _one_line_error(capsys, "replay")
    camp = tmp_path / "camp"
    camp.mkdir()
    (camp / "campaign.json").write_text('{"schema": "genesis-rl/campaign", "spec": ' + "{\"a\": " * 100_000 + "1"
                                        + "}" * 100_000 + "}")
    assert main(["report", str(camp), "--out", str(tmp_path / "report.html")]) == 2
    assert "is nested 100,001 levels deep" in _one_line_error(capsys, "report")


def test_brackets_inside_strings_do_not_count_and_the_limit_can_be_raised(monkeypatch) -> None:
    from genesis_rl.core import parsing

    assert parsing.json_depth('{"a": [1, {"b": "[[[[{{{{"}], "c": "\\\\", "d": "x\\"[[[["}') == 3
    assert parsing.json_depth(json.dumps({"s": "[" * 500})) == 1
    deep = "[" * 70 + "]" * 70
    with pytest.raises(UserInputError, match="nested 70 levels deep, over the limit of 64"):
        parsing.loads_json(deep, "x")
    monkeypatch.setenv("GENESIS_RL_MAX_NESTING", "100")
    assert parsing.loads_json(deep, "x") == json.loads(deep)
    monkeypatch.setenv("GENESIS_RL_MAX_NESTING", "5000")  # past Python's own limit: still one clean error
    with pytest.raises(UserInputError, match="deeper than Python's parser allows"):
        parsing.loads_json("[" * 3000 + "]" * 3000, "x")


def test_deep_toml_configs_and_odds_are_one_line(tmp_path, capsys) -> None:
    """tomllib recurses once a bracket (RecursionError at 1,000) and spends memory quadratic in a dotted key."""
    config = tmp_path / "deep.toml"
    config.write_text("[env]\nx = " + "[" * 200_000 + "]" * 200_000 + "\n")
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "run")]) == 2
    err = _one_line_error(capsys, "train")
    assert f"config '{config}' is nested more than 64 levels deep" in err and "GENESIS_RL_MAX_NESTING" in err
    assert not (tmp_path / "run").exists()
    odd = tmp_path / "odd.toml"
    odd.write_text("a" + ".a" * 3000 + " = 1\n")  # 100,000 segments would take tens of GB inside tomllib
    t0 = time.monotonic()
    assert main(["evaluate", "--policies", "sunny", "--odd", str(odd), "--out", str(tmp_path / "camp")]) == 2
    assert time.monotonic() - t0 < 10
    assert f"ODD '{odd}' is nested more than 64 levels deep" in _one_line_error(capsys, "evaluate")


def test_toml_depth_counts_headers_keys_and_brackets_but_not_strings() -> None:
    from genesis_rl.core import parsing

    assert parsing.toml_depth('a = """ [[[[ """\nb = \'{{{{\'  # [[[[\n') == 2
    assert parsing.toml_depth("[" + ".".join(["t"] * 80) + "]\nx = 1\n") > 64
    assert parsing.toml_depth("x = {" + "a." * 80 + "b = 1}\n") > 64
    with pytest.raises(UserInputError, match="not valid TOML"):
        parsing.loads_toml("x = [1, 2", "config 'c.toml'")
    paper = (REPO / "configs" / "paper.toml").read_text()
    assert parsing.loads_toml(paper, "paper") == __import__("tomllib").loads(paper)


def test_a_schedule_cell_over_131072_characters_is_one_line(tmp_path, capsys) -> None:
    schedule = tmp_path / "s.csv"
    schedule.write_text("step,fog_density\n0,1\n1," + "1" * 200_000 + "\n")
    assert main(["drive", "--schedule", str(schedule), "--steps", "2", "--out", str(tmp_path / "d"), "--quiet"]) == 2
    err = _one_line_error(capsys, "drive")
    assert f"schedule '{schedule}' line 3: a cell is longer than 131,072 characters" in err


def test_an_episode_log_with_a_huge_cell_is_named(tmp_path) -> None:
    from genesis_rl.training.checkpoint import csv_rows
    from genesis_rl.training.curves import read_episodes

    log = tmp_path / "episodes.csv"
    log.write_text("timesteps,reward\n1,2\n" + "3," + "9" * 200_000 + "\n")
    with pytest.raises(UserInputError, match=r"episode log '.*episodes.csv' line 3: a cell is longer than 131,072"):
        csv_rows(log)
    with pytest.raises(UserInputError, match="line 3: a cell is longer than 131,072"):
        read_episodes(tmp_path)


def test_files_over_the_size_ceiling_are_refused_before_reading(tmp_path, capsys, monkeypatch) -> None:
    record = tmp_path / "big.json"
    record.write_text(json.dumps(list(range(400_000))))  # 2.9 MB of valid JSON
    monkeypatch.setenv("GENESIS_RL_MAX_FILE_MB", "1")
    assert main(["replay", str(record), "--out", str(tmp_path / "r")]) == 2
    err = _one_line_error(capsys, "replay")
    size = record.stat().st_size / 2**20
    assert f"record '{record}' is {size:.1f} MiB, over the limit of 1 MiB" in err and "GENESIS_RL_MAX_FILE_MB" in err
    config = tmp_path / "big.toml"
    config.write_text("# padding\n" * 120_000)  # 1.2 MB, over the 1,024 KiB of a config
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "run")]) == 2
    err = _one_line_error(capsys, "train")
    assert "over the limit of 1,024 KiB" in err and "GENESIS_RL_MAX_TOML_KB" in err


# -- item 6: budgets bounded ----------------------------------------------------------------------------------
def _must_not_start(monkeypatch, module: str, name: str) -> None:
    """The work the command would start (for years): reaching it fails the test at once."""
    import importlib

    def started(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError(f"{module}.{name} started: the count was not refused")

    monkeypatch.setattr(importlib.import_module(module), name, started)


def test_corners_steps_1e12_refuses_at_once(tmp_path, capsys, monkeypatch) -> None:
    _must_not_start(monkeypatch, "genesis_rl.analysis.corners", "search_corners")
    t0 = time.monotonic()
    assert main(["corners", "--steps", "1000000000000", "--out", str(tmp_path / "c.json"), "--quiet"]) == 2
    assert time.monotonic() - t0 < 2
    err = _one_line_error(capsys, "corners")
    assert "--steps = 1,000,000,000,000, over the limit of 100,000 simulation steps" in err
    assert "GENESIS_RL_MAX_SIM_STEPS" in err


@pytest.mark.parametrize("policy", ["cmaes", "cem", "mcts", "goexplore", "corner_search"])
def test_a_search_budget_of_1e9_refuses_at_once(tmp_path, capsys, monkeypatch, policy) -> None:
    _must_not_start(monkeypatch, "genesis_rl.campaigns.campaign", "run_campaign")
    t0 = time.monotonic()
    assert main(["evaluate", "--policies", policy, "--search-budget", "1000000000", "--out",
                 str(tmp_path / "camp"), "--quiet"]) == 2
    assert time.monotonic() - t0 < 2
    err = _one_line_error(capsys, "evaluate")
    assert "--search-budget = 1,000,000,000, over the limit of 1,000 episodes a scene" in err
    assert "GENESIS_RL_MAX_SEARCH_BUDGET" in err


def test_a_replay_buffer_of_a_trillion_transitions_is_refused_not_allocated(tmp_path, capsys, monkeypatch) -> None:
    """numpy's _ArrayMemoryError (18.4 PiB) was a traceback after the envs had started."""
    _must_not_start(monkeypatch, "genesis_rl.training.train", "train")
    config = tmp_path / "sac.toml"
    config.write_text('[train]\nalgorithm = "sac"\n[sac]\nbuffer_size = 1000000000000\n')
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "run")]) == 2
    assert "sac.buffer_size = 1,000,000,000,000, over the limit of 1,000,000 transitions" in \
        _one_line_error(capsys, "train")


def test_a_campaign_file_cannot_set_a_budget_the_command_line_may_not() -> None:
    from genesis_rl.campaigns.campaign_spec import CampaignSpec

    with pytest.raises(UserInputError, match="campaign spec.steps = 1,000,000,000,000, over the limit"):
        CampaignSpec(policies=("sunny",), steps=10**12)
    with pytest.raises(UserInputError, match="campaign spec.options.search_budget = 1,000,000,000, over"):
        CampaignSpec(policies=("cmaes",), options={"search_budget": 10**9})


@pytest.mark.parametrize(("argv", "module", "name", "message"), [
    (["bench", "system", "--frames", "1000000000"], "genesis_rl.commands.speed", "bench_system",
     "--frames = 1,000,000,000, over the limit of 100,000 frames"),
    (["bench", "sim", "--frames", "1000000000"], "genesis_rl.commands.speed", "bench_sim",
     "--frames = 1,000,000,000, over the limit of 100,000 frames"),
    (["bench", "campaign", "--workers", "1,,2"], "genesis_rl.commands.speed", "bench_campaign",
     "--workers '1,,2'; allowed: a comma list of integers >= 1"),
    (["bench", "campaign", "--workers", "1,100000"], "genesis_rl.commands.speed", "bench_campaign",
     "--workers '1,100000' needs 100,000 processes, over the limit of 256"),
    (["evaluate", "--policies", "sunny", "--workers", "100000"], "genesis_rl.campaigns.campaign", "run_campaign",
     "--workers = 100,000, over the limit of 256 processes"),
    (["detector", "train", "--frames", "1000000000"], "genesis_rl.sut.perception.train", "train_detector",
     "--frames = 1,000,000,000, over the limit of 100,000 frames"),
    (["detector", "train", "--epochs", "100000000"], "genesis_rl.sut.perception.train", "train_detector",
     "--epochs = 100,000,000, over the limit of 1,000 epochs"),
    (["train", "--episode-steps", "1000000000000"], "genesis_rl.training.train", "train",
     "env.episode_steps = 1,000,000,000,000, over the limit of 100,000"),
    (["train", "--scenes", "1000000000"], "genesis_rl.training.train", "train",
     "env.scenes = 1,000,000,000, over the limit of 100,000 scenes"),
    (["train", "--n-steps", "1000000000000"], "genesis_rl.training.train", "train",
     "ppo.n_steps = 1,000,000,000,000, over the limit of 1,000,000 transitions"),
])
def test_every_count_that_sets_work_has_a_ceiling(tmp_path, capsys, monkeypatch, argv, module, name,
                                                  message) -> None:
    _must_not_start(monkeypatch, module, name)
    out = ["--out", str(tmp_path / "out")] if argv[0] in ("evaluate", "detector", "train") else []
    assert main([*argv, *out]) == 2
    err = _one_line_error(capsys, argv[0])
    assert message in err, err


# -- the Ray address check answers within seconds ---------------------------------------------------------------
@contextmanager
def _server(answer: Callable[[socket.socket], None]) -> Iterator[int]:
    """A TCP server on 127.0.0.1 that calls ``answer`` on each connection; yields its port."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held: list[socket.socket] = []

    def loop() -> None:
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            held.append(conn)
            threading.Thread(target=answer, args=(conn,), daemon=True).start()

    threading.Thread(target=loop, daemon=True).start()
    try:
        yield srv.getsockname()[1]
    finally:
        srv.close()
        for conn in held:
            conn.close()


def _silent(conn: socket.socket) -> None:
    """Accepts and never answers (a firewall holding the connection, a hung service)."""


def _http(conn: socket.socket) -> None:
    try:
        conn.recv(1024)
        conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
    except OSError:
        pass
    conn.close()


def _closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now: connection refused
    return port


def test_a_ray_address_that_does_not_answer_as_ray_is_refused_within_5_s(tmp_path, capsys) -> None:
    """Before: a TCP connect was all that was checked, and ray.init then retried for 20 s and more."""
    pytest.importorskip("ray")
    grpc = pytest.importorskip("grpc")
    from concurrent import futures

    from genesis_rl.distributed.settings import ExecutorSettings

    with _server(_silent) as port:
        t0 = time.monotonic()
        with pytest.raises(UserInputError, match=f"127.0.0.1:{port} accepts connections but does not answer as "
                                                 "Ray's GCS within 3 s"):
            ExecutorSettings("ray", ray_address=f"127.0.0.1:{port}").preflight()
        assert time.monotonic() - t0 < 5
    with _server(_http) as port:
        with pytest.raises(UserInputError, match="answers, but not as Ray's GCS"):
            ExecutorSettings("ray", ray_address=f"127.0.0.1:{port}").preflight()
    port = _closed_port()
    t0 = time.monotonic()
    assert main(["evaluate", "--policies", "sunny", "--executor", "ray", "--ray-address", f"127.0.0.1:{port}",
                 "--out", str(tmp_path / "camp"), "--quiet"]) == 2
    assert f"nothing answers at 127.0.0.1:{port}" in _one_line_error(capsys, "evaluate")
    assert not (tmp_path / "camp").exists()
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=1))  # a gRPC server, as Ray's GCS is: accepted
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        ExecutorSettings("ray", ray_address=f"127.0.0.1:{port}").preflight()
    finally:
        server.stop(0)


# -- item 7: CARLA connection errors classified -----------------------------------------------------------------
def _scenes_carla(tmp_path: Path, *flags: str) -> list[str]:
    return ["scenes", "--backend", "carla", "--map", "Town05", "--count", "1", "--out", str(tmp_path / "c.json"),
            "--quiet", *flags]


def test_a_service_that_is_not_carla_is_one_line_not_an_abort(tmp_path) -> None:
    """The carla client library aborted the process (exit 134) on an HTTP answer: run in a child process."""
    pytest.importorskip("carla")
    with _server(_http) as port:
        done = subprocess.run([sys.executable, "-m", "genesis_rl", *_scenes_carla(tmp_path, "--carla-host",
                               "127.0.0.1", "--carla-port", str(port))], capture_output=True, text=True, timeout=120,
                              env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    err = done.stderr.strip()
    assert "Traceback" not in err and err.count("\n") == 0
    assert f"127.0.0.1:{port} answers, but not as a CARLA server (not msgpack-rpc: it sent b'HTTP/1.1 400" in err


@pytest.mark.parametrize("case", ["silent", "refused", "unresolvable"])
def test_each_carla_connection_failure_is_one_classified_line(tmp_path, capsys, case) -> None:
    pytest.importorskip("carla")
    with _server(_silent) as silent_port:
        host, port = {"silent": ("127.0.0.1", silent_port), "refused": ("127.0.0.1", _closed_port()),
                      "unresolvable": ("no-such-carla-host.invalid", 2000)}[case]
        t0 = time.monotonic()
        assert main(_scenes_carla(tmp_path, "--carla-host", host, "--carla-port", str(port),
                                  "--carla-timeout", "1")) == 2
        assert time.monotonic() - t0 < 5
    err = _one_line_error(capsys, "scenes")
    assert {"silent": f"127.0.0.1:{port} accepted the connection but did not answer CARLA's version call within 1 s",
            "refused": f"nothing listens at 127.0.0.1:{port} (connection refused); start a CARLA",
            "unresolvable": "--carla-host 'no-such-carla-host.invalid' does not resolve"}[case] in err, err
    assert not (tmp_path / "c.json").exists()


def _fake_carla(conn: socket.socket) -> None:
    """Answers each msgpack-rpc 'version' call as CARLA 0.9.16 does: [1, msgid, nil, [[1, "0.9.16"]]]."""
    try:
        while True:
            data = conn.recv(4096)
            if not data:
                return
            msgid = data[2]  # a positive fixint: the first 128 calls of a connection
            conn.sendall(bytes([0x94, 0x01, msgid, 0xC0, 0x91, 0x92, 0x01, 0xA6]) + b"0.9.16")
    except OSError:
        pass


def test_a_carla_server_passes_the_probe_and_bad_numbers_are_refused(tmp_path, capsys) -> None:
    pytest.importorskip("carla")
    from genesis_rl.sim.carla.connection import connect

    with _server(_fake_carla) as port:
        assert connect("127.0.0.1", port, 2.0).get_server_version() == "0.9.16"
    for flag, value in (("--carla-timeout", "inf"), ("--carla-tm-port", "70000")):  # inf: the client made it 0 s
        with pytest.raises(SystemExit) as stop:  # refused by the flag's argparse type, before any work
            main(_scenes_carla(tmp_path, flag, value))
        assert stop.value.code == 2
        assert f"argument {flag}: '{value}': allowed:" in capsys.readouterr().err
    with pytest.raises(UserInputError, match="not a TCP port"):  # a config's value reaches the same check
        check_numbers(2000, 10.0, 70000)
    with pytest.raises(UserInputError, match=r"allowed: seconds in \(0, 3600\]"):
        check_numbers(2000, float("inf"))
