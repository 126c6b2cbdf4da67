"""Exact snapshots of a lite episode: restoring one and stepping on with the same actions gives the same step
records and camera frame, to the bit, as the uninterrupted run, on every zoo member (each has its own system
state: latency queues, stall timers, visibility estimates, trackers and random draws)."""

from __future__ import annotations

import numpy as np
import pytest

from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.sim.carla.backend import CarlaSimulation
from genesis_rl.sim.interface import SnapshotUnsupported
from genesis_rl.sut.zoo.members import ZOO, env_settings

BEFORE, AFTER = 14, 12  # steps before the snapshot, steps compared after it


def _play(env: GenesisEnv, actions: np.ndarray) -> str:
    for a in actions:
        env.step(a)
    # repr: exact for floats, and NaN (no lead seen) compares equal to itself, which == does not
    return repr(env.records[-len(actions):])


@pytest.mark.parametrize("member", sorted(ZOO))
def test_restore_steps_on_as_the_uninterrupted_run(member: str) -> None:
    env = GenesisEnv(EnvConfig(**{**env_settings(ZOO[member]), "scenes": 3, "episode_steps": 64}))
    try:
        actions = np.random.default_rng(7).uniform(-1, 1, (BEFORE + AFTER, env.action_space.shape[0]))
        actions = actions.astype(np.float32)
        env.reset(options={"scene": 1, "episode_seed": 11})
        _play(env, actions[:BEFORE])
        snap = env.snapshot()
        straight = _play(env, actions[BEFORE:])
        frame = env.camera_frame().copy()
        _play(env, -actions[BEFORE:BEFORE + 5])  # wander off first: the restore must undo it all
        obs = env.restore(snap)
        assert len(env.records) == BEFORE
        restored = _play(env, actions[BEFORE:])
        assert restored == straight
        assert np.array_equal(env.camera_frame(), frame)
        env.reset(options={"scene": 0, "episode_seed": 3})  # another scene's simulation in between
        _play(env, actions[:3])
        again_obs = env.restore(snap)
        assert _play(env, actions[BEFORE:]) == straight
        assert np.array_equal(np.asarray(obs), np.asarray(again_obs))
    finally:
        env.close()


def test_a_snapshot_does_not_copy_the_detector_network() -> None:
    """A snapshot copies the system's state, not its weights: cheap (a tenth of a step here) and shared."""
    env = GenesisEnv(EnvConfig(**{**env_settings(ZOO["low_sun"]), "scenes": 2, "episode_steps": 16}))
    try:
        env.reset(options={"scene": 0, "episode_seed": 1})
        snap = env.snapshot()
        assert snap.system is not env.system
        assert snap.system.detector._net is env.system.detector._net
        assert snap.world.traffic is not env._sim.traffic and snap.world.traffic.map is env._sim.traffic.map
    finally:
        env.close()


def test_carla_says_why_it_cannot_snapshot() -> None:
    sim = object.__new__(CarlaSimulation)  # no server needed: the refusal comes before any call to one
    with pytest.raises(SnapshotUnsupported, match="CARLA's Python API can neither read nor set") as err:
        sim.snapshot()
    assert "goexplore on the lite backend" in str(err.value)
    with pytest.raises(SnapshotUnsupported):
        sim.restore(object())
