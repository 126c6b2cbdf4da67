"""The reactivity measurement (evaluation/reactivity.py): a fixed schedule has no gap between closed-loop and
open-loop play, a policy that times its weather to what the system reports has one."""

from __future__ import annotations

import numpy as np
import pytest

from genesis_rl.analysis.reactivity import METRICS, measure
from genesis_rl.env.observation import FEATURES

CLOSE = 20.0  # [m]


def fog_timing(recs) -> float:
    """Fog while the system perceives a lead within CLOSE, minus fog at other times: a score only a policy
    that watches the scene can keep high (an open-loop schedule fogs at the wrong moments)."""
    return float(sum(r.knobs["fog_density"] / 100.0 * (1.0 if r.lead.perceived_distance < CLOSE else -1.0)
                     for r in recs))


class FogWhileClose:
    """Hand-written reactive test policy: fog up while the system perceives a lead within CLOSE, else down."""

    def __init__(self, n_knobs: int) -> None:
        self.k, self.n = n_knobs, n_knobs + len(FEATURES)

    def reset(self, scene: int, episode_seed: int) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        now = obs[-self.n :]
        close = now[self.k + FEATURES.index("follows")] > 0.5 and \
            now[self.k + FEATURES.index("perceived_gap")] * 60.0 < CLOSE
        return np.array([1.0 if close else -1.0, 0, 0, 0, 0], np.float32)


class Constant:
    def reset(self, scene: int, episode_seed: int) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.array([1.0, 1.0, 1.0, 1.0, 0.0], np.float32)


@pytest.fixture(scope="module")
def env():
    from genesis_rl.env import GenesisEnv

    e = GenesisEnv(map="highway", scenes=16, catalog_seed=0, episode_steps=100, observation="features", obs_history=1)
    yield e
    e.close()


@pytest.mark.render
def test_a_constant_schedule_has_exactly_no_gap(env) -> None:
    result = measure(env, Constant(), [0, 1, 2], [100, 101, 102], other_seeds=[200, 201, 202])
    assert len(result.rows) == 6
    for kind, gaps in result.summary().items():
        for metric in METRICS:
            g = gaps[metric]
            assert g["difference"]["mean"] == 0.0 and g["ties"] == 3, (kind, metric)


@pytest.mark.render
def test_a_reactive_policy_has_a_positive_gap(env) -> None:
    metrics = {**METRICS, "fog_timing": fog_timing}
    result = measure(env, FogWhileClose(len(env.config.knobs)), [0, 1, 2, 3], [100, 101, 102, 103], metrics=metrics)
    gap = result.gap("other_scene", "fog_timing")
    assert gap["wins"] == 4 and gap["losses"] == 0 and gap["difference"]["mean"] > 5.0
    donors = [(r.scene, r.donor_scene) for r in result.rows]
    assert donors == [(0, 1), (1, 2), (2, 3), (3, 0)]  # each scene got the next scene's actions, cyclically
    again = measure(env, FogWhileClose(len(env.config.knobs)), [0, 1], [100, 101], metrics=metrics)
    assert again.rows[0].closed == result.rows[0].closed  # the same scenes and seeds, the same episodes


def test_measure_needs_two_scenes_with_seeds() -> None:
    with pytest.raises(ValueError, match=">= 2 scenes"):
        measure(None, Constant(), [0], [1])
    with pytest.raises(ValueError, match="one per scene"):
        measure(None, Constant(), [0, 1], [1, 2], other_seeds=[])


@pytest.mark.render
def test_reactivity_command_on_a_campaign(tmp_path) -> None:
    import json
    import subprocess
    import sys

    camp = tmp_path / "camp"
    run = [sys.executable, "-m", "genesis_rl"]
    r = subprocess.run([*run, "evaluate", "--policies", "constant", "--map", "highway", "--scenes", "2", "--steps",
                        "20", "--seed", "0", "--out", str(camp), "--quiet"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    r = subprocess.run([*run, "reactivity", "--campaign", str(camp), "--policy", "constant", "--quiet"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    data = json.loads((camp / "reactivity_constant.json").read_text())
    assert {row["kind"] for row in data["rows"]} == {"other_scene", "other_seed"} and len(data["rows"]) == 4
    assert all(g["difference"]["mean"] == 0.0 for gaps in data["gaps"].values() for g in gaps.values())
    again = subprocess.run([*run, "reactivity", "--campaign", str(camp), "--policy", "constant", "--quiet"],
                           capture_output=True, text=True, timeout=600)
    assert again.returncode == 2 and "--force" in again.stderr
    for bad, message in ((["--policy", "cmaes"], "needs a step policy"), (["--scenes", "1"], "allowed: 2..2"),
                         (["--policy", "agent"], "was evaluated without an agent")):
        r = subprocess.run([*run, "reactivity", "--campaign", str(camp), "--force", *bad], capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 2 and message in r.stderr
    r = subprocess.run([*run, "reactivity", "--campaign", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 2 and "is not a campaign folder" in r.stderr
    r = subprocess.run([*run, "reactivity", "--campaign", str(camp), "--workers", "0"], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 2 and "--workers = 0; allowed: an integer >= 1" in r.stderr


@pytest.mark.render
def test_reactivity_on_two_workers_is_the_same_measurement(tmp_path) -> None:
    """A pool plays the two rounds in parallel; every row, and so every gap, is what one process measures."""
    import json
    import os
    import subprocess
    import sys

    camp = tmp_path / "camp"
    run = [sys.executable, "-m", "genesis_rl"]
    r = subprocess.run([*run, "evaluate", "--policies", "random", "--map", "highway", "--scenes", "3", "--steps",
                        "30", "--seed", "4", "--out", str(camp), "--quiet"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = {}
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}.json"
        # the one-worker run plays in the main process at 4 torch threads against the pool's one: kernels that
        # round differently with the thread count (on AMD EPYC; on Intel the detector's raw outputs) must not
        # reach the rows, since the system under test pins its own threads
        env = {**os.environ, "OMP_NUM_THREADS": "4"} if workers == "1" else None
        r = subprocess.run([*run, "reactivity", "--campaign", str(camp), "--policy", "random", "--workers", workers,
                            "--quiet", "--out", str(out)], capture_output=True, text=True, timeout=600, env=env)
        assert r.returncode == 0, r.stderr[-2000:]
        rows[workers] = json.loads(out.read_text())
    assert len(rows["1"]["rows"]) == 6 and rows["1"]["rows"] == rows["2"]["rows"]
    assert rows["1"]["gaps"] == rows["2"]["gaps"]
    # random weather reacts to nothing, yet its gap is not zero on every scene: the rows carry real episodes
    assert any(row["closed"] != row["open"] for row in rows["1"]["rows"])


def test_a_worker_that_cannot_start_raises_instead_of_hanging(tmp_path) -> None:
    """multiprocessing restarts a worker whose initializer raises, forever; the pool hands the error to the
    first episode instead, so the command stops with it."""
    from genesis_rl.analysis.reactivity import PoolPlayer

    with PoolPlayer({"env": "not a table"}, str(tmp_path), "random", 2) as pool, pytest.raises(KeyError):
        pool.closed([(0, 1)])


def test_a_campaign_pool_worker_that_cannot_start_raises_instead_of_hanging(tmp_path) -> None:
    """The campaign's episode pool (evaluation/executors.py) has the same guard: a plug-in that does not import
    in a spawned worker stops the campaign with its error."""
    from genesis_rl.campaigns.executors import WorkerSetup, run_tasks
    from genesis_rl.core.errors import UserInputError
    from genesis_rl.distributed.settings import ExecutorSettings

    setup = WorkerSetup({}, tmp_path, ("genesis_rl_no_such_plugin_module",))
    with pytest.raises(UserInputError, match="genesis_rl_no_such_plugin_module"):
        list(run_tasks([("random", 0, 1), ("random", 1, 2)], setup, ExecutorSettings(workers=2)))
