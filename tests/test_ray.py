"""Campaigns on Ray: the same summary as the local executor whatever the number of workers, a killed
worker's episode retried, and bad scale-out settings refused before anything is written."""

from __future__ import annotations

import json
import os
import signal
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from genesis_rl.campaigns.campaign import CampaignSpec, ExecutorSettings, run_campaign
from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.distributed.servers import CarlaServer, NodeServer, parse_servers, servers_for_workers

ray = pytest.importorskip("ray", reason="scripts/test.sh installs the ray extra; CI runs these")  # see test.sh
PLUGINS = Path(__file__).parent / "plugins"
STEPS = 60


@pytest.fixture(scope="module")
def crash_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("crash")


@pytest.fixture(scope="module")
def local_ray(crash_dir):
    """One local Ray instance for the module (campaigns reuse an instance they did not start). The crash
    policy's settings are in the environment before Ray starts, so its workers inherit them."""
    os.environ["GENESIS_RL_TEST_CRASH_DIR"] = str(crash_dir)
    os.environ["GENESIS_RL_TEST_CRASH_SCENE"] = "5"
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    ray.init(num_cpus=2, resources={"carla_server": 2}, include_dashboard=False, log_to_driver=False,
             logging_level="ERROR")
    yield ray
    ray.shutdown()
    for signum, handler in handlers.items():  # ray.init leaves its sys.exit SIGTERM handler in the process
        signal.signal(signum, handler)


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> str:
    from genesis_rl.sim.lite.scenes import generate_catalog

    path = tmp_path_factory.mktemp("cat") / "highway.json"
    generate_catalog("highway", 12, 0).save(path)
    return str(path)


def _spec(catalog: str, policies=("sunny", "random")) -> CampaignSpec:
    # the blind system never sees a vehicle: scene 5 (seed 1) ends in a collision, so records and frames are
    # written and travel back from the workers
    return CampaignSpec(policies=policies, catalog=catalog, scenes=3, seed=1, steps=STEPS, env={"system": "blind"})


def _stable(folder: Path) -> dict:
    summary = json.loads((folder / "summary.json").read_text())
    return {k: v for k, v in summary.items() if k not in ("campaign", "run_seconds", "workers", "executor")}


def _files(folder: Path) -> dict[str, int]:
    """Every result file and its size (the rows' timings aside, which differ between runs)."""
    files = {p.relative_to(folder).as_posix(): p.stat().st_size for p in folder.rglob("*") if p.is_file()}
    return {k: v for k, v in files.items() if not k.startswith("episodes/")
            and k not in ("run_time.json", "summary.json", "campaign.json", "episodes.csv")}


@pytest.mark.render
def test_ray_campaigns_with_1_and_2_workers_equal_the_local_one(tmp_path, catalog, local_ray, monkeypatch) -> None:
    # earlier tests in the session registered policies from tests/plugins; workers import those modules again,
    # so the folder must be importable, as a user's plug-ins are
    monkeypatch.syspath_prepend(str(PLUGINS))
    local = tmp_path / "local"
    run_campaign(_spec(catalog), local, progress=False)
    for workers in (1, 2):
        folder = tmp_path / f"ray{workers}"
        run_campaign(_spec(catalog), folder, progress=False, executor=ExecutorSettings("ray", workers))
        assert _stable(folder) == _stable(local)
        assert _files(folder) == _files(local)
        assert json.loads((folder / "run_time.json").read_text())["executor"] == "ray"
    s = _stable(local)
    assert s["policies"]["random"]["episodes_with_collision"] == 1  # the campaign has a failure to carry
    assert any((tmp_path / "ray2" / "records").glob("*.json")) and any((tmp_path / "ray2" / "frames").rglob("*.jpg"))
    # a Ray campaign resumes like a local one: one episode removed, one run again, same summary
    (tmp_path / "ray2" / "episodes" / "random" / "scene_0005.json").unlink()
    summary = run_campaign(_spec(catalog), tmp_path / "ray2", resume=True, progress=False,
                           executor=ExecutorSettings("ray", 2))
    assert json.loads((tmp_path / "ray2" / "run_time.json").read_text())["episodes_run"] == 1
    assert summary["policies"] == json.loads((local / "summary.json").read_text())["policies"]


@pytest.mark.render
def test_a_killed_ray_worker_costs_one_retried_episode(tmp_path, catalog, local_ray, crash_dir, monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(PLUGINS))
    import crash_once  # noqa: F401 - registers the policy; the workers import it again

    from genesis_rl.adversaries.base import POLICIES

    spec = _spec(catalog, policies=("sunny", "crash_once"))
    folder = tmp_path / "crash"
    try:
        summary = run_campaign(spec, folder, progress=False, executor=ExecutorSettings("ray", 2))
    finally:  # the policy leaves with this test: a later pool campaign in this worker would import its module
        POLICIES.pop("crash_once", None)  # again, and tests/plugins is then no longer on the path
        sys.modules.pop("crash_once", None)
    assert (crash_dir / "crashed_5").is_file()  # the worker did die once
    assert summary["complete"] and summary["policies"]["crash_once"]["episodes"] == 3
    # the retried episode is the episode: crash_once plays sunny weather, so its results are sunny's
    a, b = summary["policies"]["sunny"], summary["policies"]["crash_once"]
    assert a["collision"] == b["collision"] and a["episodes_with_collision"] == b["episodes_with_collision"] == 1


# -- bad input: exit 2, nothing written ---------------------------------------------------------------------
def _evaluate(tmp_path, *extra: str) -> tuple[int, Path]:
    out = tmp_path / "camp"
    rc = main(["evaluate", "--policies", "sunny", "--scenes", "1", "--steps", "5", "--out", str(out), "--quiet",
               "--no-report", *extra])
    return rc, out


def test_an_unreachable_ray_address_is_refused_before_anything_is_written(tmp_path, capsys) -> None:
    rc, out = _evaluate(tmp_path, "--executor", "ray", "--ray-address", "127.0.0.1:9")
    assert rc == 2 and not out.exists()
    assert "nothing answers at 127.0.0.1:9" in capsys.readouterr().err
    rc, out = _evaluate(tmp_path, "--executor", "ray", "--ray-address", "no-port")
    assert rc == 2 and not out.exists()
    assert "allowed: HOST:PORT" in capsys.readouterr().err
    rc, out = _evaluate(tmp_path, "--ray-address", "127.0.0.1:6379")
    assert rc == 2 and "--ray-address needs --executor ray" in capsys.readouterr().err


def _client_server(cluster_info=None):  # noqa: ANN001, ANN202
    """A gRPC server on a free loopback port; with ``cluster_info`` a Ray Client server whose ClusterInfo (the
    client's PING) it answers, without one a gRPC server of no Ray service (as a GCS is to Ray's client)."""
    from concurrent import futures

    import grpc
    from ray.core.generated import ray_client_pb2_grpc

    server = grpc.server(futures.ThreadPoolExecutor(2))
    if cluster_info is not None:
        class Servicer(ray_client_pb2_grpc.RayletDriverServicer):
            def ClusterInfo(self, request, context):  # noqa: ANN001, ANN202, N802
                return cluster_info(request, context)

        ray_client_pb2_grpc.add_RayletDriverServicer_to_server(Servicer(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    return server, port


#: what Ray Client raised after ~43 s when the head's proxy could not start the client's session
PROXY_FAILURE = """Initialization failure from server:
Traceback (most recent call last):
  File "/venv/lib/python3.11/site-packages/ray/util/client/server/proxier.py", line 772, in Datapath
    raise RuntimeError(
RuntimeError: Starting Ray client server failed. See ray_client_server_23000.err for detailed logs.
"""


def test_a_ray_client_address_gets_one_line_and_the_fix(tmp_path, capsys, monkeypatch) -> None:
    """ray:// at a port that is not Ray's Client server (the GCS's) or at a cluster that wants a token: Ray's
    client retried its PING for 30 s and more, then said only "ray client connection timeout". Ray Client's
    PING is asked within the 3 s check now. A session the head could not start came as Ray's multi-line server
    traceback inside the error line: one line now, the traceback's last line in it."""
    import time

    import grpc
    from ray.core.generated import ray_client_pb2

    def unauthenticated(request, context):  # noqa: ANN001, ANN202 - what a head with token auth answers
        context.abort(grpc.StatusCode.UNAUTHENTICATED, "Invalid or missing authentication token")

    for info, expected in [(None, "is a gRPC server but not Ray's Client server (ray:// needs the head's Ray Client "
                                  "port, 10001 unless ray start --ray-client-server-port set another); a cluster's "
                                  "GCS port is given without ray://: --ray-address 127.0.0.1:"),
                           (unauthenticated, "the cluster wants a token (Ray's token authentication) and this command "
                                             "sent none or another; set RAY_AUTH_MODE=token")]:
        server, port = _client_server(info)
        try:
            t0 = time.monotonic()
            rc, out = _evaluate(tmp_path, "--executor", "ray", "--ray-address", f"ray://127.0.0.1:{port}")
            took = time.monotonic() - t0
        finally:
            server.stop(None)
        err = capsys.readouterr().err
        assert rc == 2 and not out.exists() and took < 5, (rc, took, err)
        assert err.count("\n") == 1 and expected in err, err

    server, port = _client_server(lambda request, context: ray_client_pb2.ClusterInfoResponse(json="{}"))
    monkeypatch.setattr(ray, "is_initialized", lambda: False)

    def refused(**kwargs) -> None:  # noqa: ANN003
        raise ConnectionAbortedError(PROXY_FAILURE)

    monkeypatch.setattr(ray, "init", refused)
    from genesis_rl.distributed.ray_cluster import ray_session

    try:  # (the session starts once the campaign has its scenes: asked directly here, it is quicker)
        with pytest.raises(UserInputError) as e, ray_session(f"ray://127.0.0.1:{port}", 1):
            pass
    finally:
        server.stop(None)
    assert str(e.value) == (
        f"--ray-address = 'ray://127.0.0.1:{port}': the Ray Client server there could not start this command's session "
        "(Ray: \"Starting Ray client server failed. See ray_client_server_23000.err for detailed logs\"; Ray's logs "
        "are on the head, in /tmp/ray/session_latest/logs by default); run the command again, or connect without Ray "
        "Client: --ray-address HOST:6379 (the head's GCS port) from a machine that reaches every node, or auto on the "
        "head")


def test_ray_not_installed_names_the_extra(tmp_path, capsys, monkeypatch) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    rc, out = _evaluate(tmp_path, "--executor", "ray")
    assert rc == 2 and not out.exists()
    assert "pip install -e .[ray]" in capsys.readouterr().err


def test_carla_workers_need_one_server_each(tmp_path, capsys) -> None:
    assert parse_servers("a:2000, b:3000:9000") == (CarlaServer("a", 2000, 8000), CarlaServer("b", 3000, 9000))
    assert servers_for_workers("lite", (), 4) == [None] * 4
    with pytest.raises(UserInputError, match="names the RPC port a:2000 twice"):
        parse_servers("a:2000,a:2000:9000")
    with pytest.raises(UserInputError, match="traffic-manager port 8000 to two workers"):
        parse_servers("a:2000,a:3000:8000")
    # issue 36: traffic managers listen on this machine, so two hosts' servers on one port would share 8000
    with pytest.raises(UserInputError, match=r"port 8000 to two workers \(hostA:2000:8000, hostB:2000:8000\)"):
        parse_servers("hostA:2000,hostB:2000")
    assert parse_servers("hostA:2000,hostB:2000:8001")[1].tm_port == 8001
    with pytest.raises(UserInputError, match="has port 'x'"):
        parse_servers("a:x")
    rc, out = _evaluate(tmp_path, "--backend", "carla", "--workers", "2")
    assert rc == 2 and not out.exists()
    assert "would tick one CARLA server from 2 processes" in capsys.readouterr().err
    rc, out = _evaluate(tmp_path, "--backend", "carla", "--workers", "3", "--carla-servers", "h:2000,h:3000")
    assert rc == 2 and not out.exists()
    assert "--workers = 3 but --carla-servers names 2 server(s)" in capsys.readouterr().err


def test_carla_servers_as_ray_resources(tmp_path, capsys, local_ray) -> None:
    """--carla-servers ray: each worker holds one 'carla_server' resource of its node and drives that node's
    server at 127.0.0.1; Ray places no two workers on one server, and too few servers are refused up front."""
    import gymnasium as gym

    from genesis_rl.distributed.ray_cluster import ray_session
    from genesis_rl.training.ray_vec_env import RayVecEnv

    (node,) = parse_servers("ray")
    assert node == NodeServer("127.0.0.1", 2000, 8000) and parse_servers("ray:3000") == (NodeServer(port=3000,
                                                                                                   tm_port=9000),)
    assert servers_for_workers("carla", (node,), 3) == [node] * 3
    assert node.env_settings() == {"carla_host": "127.0.0.1", "carla_port": 2000, "carla_tm_port": 8000}
    with pytest.raises(UserInputError, match="has port 'x'"):
        parse_servers("ray:x")
    with pytest.raises(UserInputError, match="add --executor ray"):
        ExecutorSettings("local", 2, servers=(node, node))
    settings = ExecutorSettings("ray", 2, servers=(node, node))
    assert settings.ray_resources(1) == {"carla_server": 1.0} and settings.server(1)["carla_host"] == "127.0.0.1"

    # two envs hold both of the local Ray's servers while they live, and step
    env = RayVecEnv([lambda: gym.make("CartPole-v1")] * 2, None, settings.ray_resources(0))
    try:
        env.reset()
        env.step(env.action_space.sample()[None].repeat(2, 0))
        assert ray.available_resources().get("carla_server", 0) == 0
    finally:
        env.close()
    # more workers than the cluster has servers: refused with the fix, not a wait forever
    with pytest.raises(UserInputError, match=r"offers 2; start each node .* ray start --resources"), \
            ray_session(None, 2, {"carla_server": 1.5}):
        pass
    rc, out = _evaluate(tmp_path, "--backend", "carla", "--workers", "2", "--carla-servers", "ray")
    assert rc == 2 and not out.exists() and "add --executor ray" in capsys.readouterr().err


# -- training envs on Ray -------------------------------------------------------------------------------------
@pytest.mark.render
def test_ray_training_envs_give_the_agent_subprocess_envs_give(tmp_path, local_ray) -> None:
    """512 steps (one rollout of 256 steps in each of two envs, and its update) with the envs as Ray actors and as
    subprocesses, same seeds: bit-identical weights and episodes."""
    import torch
    from stable_baselines3 import PPO

    from genesis_rl.env.genesis_env import EnvConfig
    from genesis_rl.training.config import PPOConfig, RunConfig, TrainConfig
    from genesis_rl.training.train import train

    cfg = RunConfig(env=EnvConfig(map="urban", scenes=4, episode_steps=64, obs_width=48, obs_height=36,
                                  system="blind"),
                    ppo=PPOConfig(n_steps=256, batch_size=128, n_epochs=2, device="cpu"),
                    train=TrainConfig(total_timesteps=512, envs=2, seed=3, checkpoint_every=512))
    train(cfg, tmp_path / "subproc", progress=False)
    train(cfg, tmp_path / "ray", progress=False, scale=ExecutorSettings("ray"))
    a = PPO.load(tmp_path / "subproc" / "agent.zip", device="cpu").policy.state_dict()
    b = PPO.load(tmp_path / "ray" / "agent.zip", device="cpu").policy.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["action_net.weight"], torch.zeros_like(a["action_net.weight"]))
    ep_a = (tmp_path / "subproc" / "episodes.csv").read_text()
    assert ep_a == (tmp_path / "ray" / "episodes.csv").read_text() and ep_a.count("\n") == 512 // 64 + 1


def test_train_with_a_bad_ray_address_writes_nothing(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    rc = main(["train", "--out", str(out), "--steps", "64", "--quiet", "--executor", "ray",
               "--ray-address", "127.0.0.1:9"])
    assert rc == 2 and not out.exists()
    assert "nothing answers at 127.0.0.1:9" in capsys.readouterr().err
    from genesis_rl.training.config import load_run_config
    from genesis_rl.training.train import check_scale

    cfg = load_run_config(None, {"train": {"envs": 2}})
    with pytest.raises(UserInputError, match="--envs = 2 but --carla-servers names 1 server"):
        check_scale(replace(cfg, env=replace(cfg.env, backend="carla", catalog="c.json")),
                    ExecutorSettings(servers=parse_servers("h:2000")))
