"""Rulebook, reward and the Gymnasium environment."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.loop.rules.reward import PaperReward, RewardConfig
from genesis_rl.loop.rules.rulebook import build_rulebook, default_rulebook, load_rulebook
from genesis_rl.world.step_record import synthetic_step


def _rec(speed=10.0, gap=float("nan"), lead_speed=float("nan"), collision=False, collision_speed=0.0):
    return synthetic_step(ego_speed=speed, lead_gap=gap, lead_speed=lead_speed, collision=collision,
                          collision_speed=collision_speed)


# -- rules ---------------------------------------------------------------------------------------------
def test_rule_terms_match_the_paper() -> None:
    rb = default_rulebook()
    assert rb.names == ["collision", "proximity", "rss_deficit"]
    assert rb.step_terms(_rec(collision=True, collision_speed=7.5))["collision"] == 7.5
    assert rb.step_terms(_rec(speed=4.0, gap=4.9, lead_speed=4.0))["proximity"] == 4.0
    assert rb.step_terms(_rec(speed=4.0, gap=5.1, lead_speed=4.0))["proximity"] == 0.0
    # d_min = (20^2 - 10^2) / (2 * 5) = 30 m; at a 12 m gap the deficit is 18 m
    assert rb.step_terms(_rec(speed=20.0, gap=12.0, lead_speed=10.0))["rss_deficit"] == pytest.approx(18.0)
    assert rb.step_terms(_rec(speed=10.0, gap=1.0, lead_speed=12.0))["rss_deficit"] == 0.0
    assert rb.step_terms(_rec(speed=20.0))["rss_deficit"] == 0.0  # no lead


def test_trajectories_compare_rule_by_rule_in_priority_order() -> None:
    rb = default_rulebook()
    crash_slow = [_rec(collision=True, collision_speed=1.0)]
    tailgate_a_lot = [_rec(speed=10.0, gap=2.0, lead_speed=10.0)] * 50
    assert rb.compare(tailgate_a_lot, crash_slow) == -1  # any collision outranks any proximity
    assert rb.compare(crash_slow, tailgate_a_lot) == 1
    assert rb.compare(crash_slow, crash_slow) == 0


def test_rulebook_toml_errors_name_the_key(tmp_path) -> None:
    assert load_rulebook("configs/rulebook.toml").names == ["collision", "proximity", "rss_deficit"]
    bad = tmp_path / "r.toml"
    bad.write_text('[[rules]]\nname = "speeding"\n')
    with pytest.raises(UserInputError, match="unknown rule 'speeding'; allowed: collision, proximity, rss_deficit"):
        load_rulebook(bad)
    bad.write_text('[[rules]]\nname = "proximity"\nparams = { radius = 3.0 }\n')
    with pytest.raises(UserInputError, match="rule 'proximity' has no parameter 'radius'; allowed: distance"):
        load_rulebook(bad)
    rb = build_rulebook([{"name": "proximity", "priority": 2}, {"name": "collision", "priority": 1}])
    assert rb.names == ["collision", "proximity"]


def test_reward_is_the_papers_formula() -> None:
    r = PaperReward()
    rb = default_rulebook()
    crash = rb.step_terms(_rec(speed=10.0, collision=True, collision_speed=10.0, gap=0.0, lead_speed=0.0))
    # a collision at 10 m/s with the lead at 0 m (so also proximity at 10 m/s), IoU 0.5
    assert r.terms(0.5, crash)["reward"] == pytest.approx(math.exp(-0.5) + math.log(1 + 500 * 10 + 100 * 10))
    assert r.terms(0.5, {"collision": 10.0})["reward"] == pytest.approx(math.exp(-0.5) + math.log(1 + 5000))
    t = r.terms(0.25, {"collision": 3.0, "proximity": 0.0})
    assert t["reward"] == pytest.approx(math.exp(-0.25) + math.log(1 + 500 * 3.0))
    t = r.terms(1.0, {"collision": 0.0, "proximity": 2.0})
    assert t["reward_behaviour"] == pytest.approx(math.log(1 + 100 * 2.0))
    assert PaperReward(RewardConfig(collision_weight=0, proximity_weight=0)).terms(0.0, {"collision": 9})[
        "reward"
    ] == pytest.approx(1.0)


# -- the environment -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def env():
    from genesis_rl.env import GenesisEnv

    e = GenesisEnv(system="oracle", scenes=8, episode_steps=12)
    yield e
    e.close()


@pytest.mark.render
def test_env_passes_gymnasium_and_sb3_checkers(env) -> None:
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=True)


@pytest.mark.render
def test_env_step_template_limits_knobs_and_reports_every_term(env) -> None:
    obs, info = env.reset(seed=3)
    assert obs.shape == (72, 96, 3) and obs.dtype == np.uint8
    before = np.array(list(info["knobs"].values()))
    obs, reward, terminated, truncated, info = env.step(np.ones(5, np.float32) * 7.0)  # clipped to +1
    after = np.array(list(info["knobs"].values()))
    span = np.array([100, 100, 100, 180, 360])
    step = np.abs(after - before) / span
    assert np.all(step <= 0.05 + 1e-9)
    assert step[0] == pytest.approx(0.05)  # fog 0 -> 5
    for key in ("iou", "rules", "reward_perception", "reward_behaviour", "ego_speed", "knobs"):
        assert key in info
    assert list(info["rules"]) == ["collision", "proximity", "rss_deficit"]  # every rule of the rulebook, by name
    assert reward == pytest.approx(info["reward_perception"] + info["reward_behaviour"])
    for _ in range(11):
        *_, terminated, truncated, info = env.step(env.action_space.sample())
    assert truncated and not terminated and "episode_violations" in info


@pytest.mark.render
def test_env_same_seed_same_episode(env) -> None:
    def roll(seed: int):
        obs, info = env.reset(seed=seed)
        out = [(info["scene"], info["episode_seed"], obs.sum())]
        for k in range(6):
            obs, r, *_ = env.step(np.full(5, 0.5 if k % 2 else -0.3, np.float32))
            out.append((r, obs.sum()))
        return out

    assert roll(11) == roll(11)
    assert roll(11) != roll(12)


@pytest.mark.render
def test_disabled_knobs_stay_at_their_start() -> None:
    from genesis_rl.env import GenesisEnv

    e = GenesisEnv(system="blind", scenes=2, episode_steps=5, disabled_knobs=("fog_density", "precipitation"))
    try:
        e.reset(seed=0)
        for _ in range(5):
            *_, info = e.step(np.ones(5, np.float32))
        assert info["knobs"]["fog_density"] == 0.0 and info["knobs"]["precipitation"] == 0.0
        assert info["knobs"]["precipitation_deposits"] == pytest.approx(25.0)
    finally:
        e.close()


def test_env_rejects_unknown_settings() -> None:
    from genesis_rl.env import GenesisEnv

    with pytest.raises(UserInputError, match="unknown env setting\\(s\\) \\['fog'\\]"):
        GenesisEnv(fog=3)


@pytest.mark.parametrize(("toml", "message"), [
    ('[[rules]]\nname = "proximity"\nparams = { distance = nan }\n', "proximity.distance = nan must be a finite"),
    ('[[rules]]\nname = "proximity"\nparams = { distance = inf }\n', "proximity.distance = inf must be a finite"),
    ('[[rules]]\nname = "proximity"\nparams = { distance = -5.0 }\n', "proximity.distance = -5.0 must be a positive"),
    ('[[rules]]\nname = "rss_deficit"\nparams = { decel = 0 }\n', "rss_deficit.decel = 0.0 must be a positive"),
    ('[[rules]]\nname = "collision"\npriority = 1\n[[rules]]\nname = "proximity"\npriority = 1\n',
     "two rules share a priority ([1, 1])"),
    ('rules = "collision"\n', "`rules` must be a list of tables ([[rules]]), got str"),
    ('rules = ["collision"]\n', "rules[0] must be a table with name, priority, params; got 'collision'"),
    ('[[rules]]\nname = "proximity"\nparams = 5\n', "params = 5 must be a table"),
    ('[[rules]]\nname = 3\n',
     "name = 3; allowed: collision, proximity, rss_deficit, speed_for_visibility or package.module:Class"),
    ('[[rules]]\nname = "no_such_module_xyz:Rule"\n', "cannot import module 'no_such_module_xyz'"),
    ('[[rules]]\nname = "genesis_rl.world.knobs:KnobSpec"\n',
     "class KnobSpec is not a genesis_rl.loop.rules.rulebook.Rule"),
])
def test_bad_rulebooks_are_refused_naming_the_field(tmp_path, toml: str, message: str) -> None:
    """Issue 21 item 5: NaN, inf and non-positive parameters scored silently before (proximity with distance =
    nan scored 0); duplicated priorities were accepted; wrong types ended in tracebacks."""
    path = tmp_path / "rulebook.toml"
    path.write_text(toml)
    with pytest.raises(UserInputError) as err:
        load_rulebook(path)
    assert message in str(err.value)


def test_a_rulebook_that_is_not_utf8_is_named(tmp_path) -> None:
    path = tmp_path / "rulebook.toml"
    path.write_bytes(b'[[rules]]\nname = "collision" # \xff\n')
    with pytest.raises(UserInputError, match=f"rulebook '{path}' is not UTF-8 text"):
        load_rulebook(path)
