"""The falsification objective: the first in-ODD collision pays and ends the episode, closeness is shaped by the
worst danger so far (summing to it), the detector's loss is capped, and a near miss cannot outscore a failure."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from genesis_rl.analysis.objectives import ScoredEpisode, falsification_return, separation
from genesis_rl.core.errors import UserInputError
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.loop.rules.danger import COLLISION_DANGER
from genesis_rl.loop.rules.reward import FalsificationReward, RewardConfig
from genesis_rl.sut.zoo.members import ZOO, env_settings


def _rec(gap: float, ego: float = 15.0, lead: float = 10.0, collided: bool = False, odd: str = "inside",
         iou: float = 1.0) -> SimpleNamespace:
    return SimpleNamespace(iou=iou, odd_status=odd, collision=SimpleNamespace(collided=collided),
                           ego=SimpleNamespace(speed=ego),
                           lead=SimpleNamespace(present=True, true_distance=gap, speed=lead, detected=True))


def test_shaping_sums_to_the_worst_danger_and_the_failure_pays_on_top() -> None:
    reward = FalsificationReward(RewardConfig(objective="falsification"), episode_steps=100)
    steps = [_rec(40.0), _rec(10.0), _rec(20.0), _rec(5.0), _rec(0.0, collided=True)]
    terms = [reward.step_terms(r, {}) for r in steps]
    closeness = [t["reward_closeness"] for t in terms]
    assert sum(closeness) == pytest.approx(10.0 * COLLISION_DANGER)  # potential-based: the worst danger, once
    assert closeness[2] == 0.0  # falling back pays nothing and costs nothing
    assert [t["reward_failure"] for t in terms] == [0.0, 0.0, 0.0, 0.0, 100.0]
    assert all(t["reward_perception"] == pytest.approx(10.0 / 100 * np.exp(-1.0)) for t in terms)
    reward.reset()
    near_miss = sum(reward.step_terms(r, {}, 0.0)["reward"] for r in [_rec(0.5, iou=0.0)] * 100)
    reward.reset()
    failure = sum(reward.step_terms(r, {})["reward"] for r in steps)
    assert near_miss < 10.0 * COLLISION_DANGER + 10.0 < 100.0 < failure  # a whole episode of near miss, blind


def test_a_collision_outside_the_odd_neither_pays_nor_ends_the_episode() -> None:
    reward = FalsificationReward(RewardConfig(objective="falsification"), episode_steps=10)
    rec = _rec(0.0, collided=True, odd="outside")
    assert not reward.is_failure(rec) and reward.step_terms(rec, {})["reward_failure"] == 0.0
    assert FalsificationReward(RewardConfig(objective="falsification"), with_odd=False).is_failure(rec)


def test_bad_settings_name_the_field_and_what_is_allowed() -> None:
    with pytest.raises(UserInputError, match="env.reward.objective = 'fail'; allowed: paper, falsification"):
        RewardConfig(objective="fail")
    with pytest.raises(UserInputError, match="must stay under failure_reward = 30"):
        RewardConfig(objective="falsification", failure_reward=30.0)


@pytest.mark.render
def test_the_env_ends_at_the_first_in_odd_failure_and_a_snapshot_keeps_the_worst_danger() -> None:
    """latency_braking's lead braking hard (every knob at +1): scene 2 fails inside its ODD at step 73."""
    env = GenesisEnv(EnvConfig(**{**env_settings(ZOO["latency_braking"]), "scenes": 4, "episode_steps": 200,
                                  "reward": RewardConfig(objective="falsification")}))
    try:
        action = np.ones(env.action_space.shape[0], np.float32)
        env.reset(options={"scene": 2, "episode_seed": 1})
        rewards = []
        for _ in range(40):
            rewards.append(env.step(action)[1])
        snap = env.snapshot()
        terminated = False
        while not terminated:
            _, r, terminated, truncated, _ = env.step(action)
            rewards.append(r)
            assert not truncated
        assert len(env.records) == 73 and env.records[-1].collision.collided
        assert env.records[-1].odd_status in ("inside", "boundary")
        assert 100.0 < sum(rewards) < 100.0 + 10.0 * COLLISION_DANGER + 10.0
        env.restore(snap)
        again = [env.step(action)[1] for _ in range(33)]
        assert again == rewards[40:]  # the worst danger so far came back with the snapshot
    finally:
        env.close()


def test_separation_is_the_chance_a_failure_outscores_a_non_failure() -> None:
    def ep(failed: bool, paper: float, falsification: float) -> ScoredEpisode:
        return ScoredEpisode("c", "p", 0, failed, paper, falsification, 0.0)

    episodes = [ep(True, 169.0, 120.0), ep(False, 127.5, 20.0), ep(False, 300.0, 12.0), ep(True, 300.0, 110.0)]
    assert separation(episodes, "paper") == pytest.approx((1 + 0 + 1 + 0.5) / 4)
    assert separation(episodes, "falsification") == 1.0
    assert separation([ep(True, 1.0, 1.0)], "paper") is None


def test_the_falsification_return_of_a_record_stops_at_its_first_in_odd_failure() -> None:
    records = [_rec(30.0), _rec(0.0, collided=True), _rec(0.0, collided=True)]
    for r in records:
        r.rules = {}
    assert falsification_return(records) == pytest.approx(
        2 * 10.0 / 3 * np.exp(-1.0) + 10.0 * COLLISION_DANGER + 100.0)
