"""genesis-rl estimate (issue 34): the estimator on a toy problem with a known answer, the likelihood ratio by
hand, the degeneracy warning, determinism, the nominal model's ranges and the command's refusals."""

from __future__ import annotations

import math
from pathlib import Path
from statistics import NormalDist

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.estimation import estimator
from genesis_rl.estimation.nominal import BEARING, NominalModel, StartRange, check_starts, load_starts
from genesis_rl.estimation.proposal import StartProposal, TruncatedNormal, elite
from genesis_rl.estimation.run import EstimateSpec, play_stages, summarise

ALT = StartRange("sun_altitude_angle", 0.0, 90.0)
BEAR = StartRange(BEARING, -180.0, 180.0)
NOMINAL = NominalModel((ALT, BEAR), action_dim=3)
#: the toy system fails, with probability 1/2, when the sun is under 10 deg and within 30 deg of ahead
TOY_P = (10 / 90) * (60 / 360) * 0.5


def toy_play(tasks):
    """A synthetic system with a closed-form failure probability under NOMINAL (TOY_P); its score rises as the
    start nears the region, as a danger score does."""
    for t in tasks:
        alt, bear = t.start["sun_altitude_angle"], t.start[BEARING]
        coin = np.random.default_rng(list(t.action_seed)).uniform() < 0.5
        failed = bool(alt < 10 and abs(bear) < 30 and coin)
        score = -(max(0.0, alt - 10) / 90 + max(0.0, abs(bear) - 30) / 180)
        yield toy_row(t, failed, score, "toy")


def toy_row(t, failed: bool, danger: float, cluster: str) -> dict:
    """The row a played episode writes (episodes.play's), for a toy whose episodes are 10 steps inside the ODD."""
    return {"index": t.index, "scene": t.scene, "episode_seed": t.episode_seed,
            **{f"start_{k}": v for k, v in t.start.items()}, "heading": 0.0, "steps": 10, "score": danger,
            "danger": danger, "in_odd_steps": 10, "failed": failed, "fail_step": 3 if failed else None,
            "cluster": cluster if failed else None}


def toy_estimate(seed: int, method: str = "importance", episodes: int = 120) -> tuple[estimator.Estimate, list]:
    spec = EstimateSpec(member="glare_blind", method=method, episodes=episodes, seed=seed,
                        stages=4 if method == "importance" else 1)
    rows: list = []
    play_stages(spec, NOMINAL, 50, rows, toy_play)
    used = [r for r in rows if r["stage"] in spec.estimate_stages]
    failed = [r["failed"] for r in used]
    est = estimator.crude(failed) if method == "crude" else estimator.importance(failed,
                                                                               [r["log_weight"] for r in used])
    return est, rows


def test_importance_sampling_is_unbiased_on_a_toy_with_a_known_answer() -> None:
    estimates = [toy_estimate(seed)[0] for seed in range(30)]
    values = np.array([e.probability for e in estimates])
    # unbiased: the mean of 30 runs within 12 % of the closed form (its standard error is about 5 %)
    assert abs(values.mean() - TOY_P) < 0.12 * TOY_P, (values.mean(), TOY_P)
    covered = sum(e.ci95[0] <= TOY_P <= e.ci95[1] for e in estimates)
    assert covered >= 25, covered  # a 95 % interval covers the truth in most runs (55 % before WIDEN_FINAL)
    # and it concentrates: 120 episodes in all give a relative half-width crude Monte Carlo needs ~10x more for
    median = float(np.median([e.relative_half_width for e in estimates]))
    assert median < 0.7 and estimator.episodes_for(TOY_P, median) > 8 * 120, median


def test_cross_entropy_moves_the_proposal_onto_the_failure_region() -> None:
    last_failures = []
    for seed in range(10):
        _, seed_rows = toy_estimate(seed)
        last = [r for r in seed_rows if r["stage"] == 3]
        assert len(last) == 60
        last_failures.append(sum(r["failed"] for r in last))
    # nominal draws: 0.9 % fail, 0.6 of 60; the adapted proposal over ten times that in most runs
    assert np.median(last_failures) >= 7, last_failures
    est, rows = toy_estimate(0)
    spec = EstimateSpec(member="glare_blind", method="importance", episodes=120, seed=0)
    from genesis_rl.estimation.run import proposal_for

    p = proposal_for(3, rows, spec, NOMINAL).normals
    assert p[0].mean < 15 and abs(p[1].mean) < 40


def test_crude_monte_carlo_agrees_and_bounds_zero_failures() -> None:
    est, _ = toy_estimate(0, method="crude", episodes=400)
    assert est.ci95[0] <= TOY_P <= est.ci95[1]
    zero = estimator.crude([False] * 1000)
    assert zero.probability == 0 and 0.0029 < zero.ci95[1] < 0.0038  # the rule of three, exactly: 3.69e-3


def test_the_likelihood_ratio_of_a_crafted_start_by_hand() -> None:
    proposal = StartProposal(NOMINAL, (TruncatedNormal(ALT, 5.0, 10.0), TruncatedNormal(BEAR, 0.0, 20.0)), 0.2)
    start = {"sun_altitude_angle": 7.0, BEARING: 10.0}
    n = NormalDist()
    alt = math.exp(-0.5 * 0.2**2) / (10 * math.sqrt(2 * math.pi)) / (n.cdf(8.5) - n.cdf(-0.5))
    bear = math.exp(-0.5 * 0.5**2) / (20 * math.sqrt(2 * math.pi)) / (n.cdf(9) - n.cdf(-9))
    nominal = 1 / (90 * 360)
    q = 0.2 * nominal + 0.8 * alt * bear
    assert proposal.log_pdf(start) == pytest.approx(math.log(q), rel=1e-12)
    assert NOMINAL.start_log_density(start) == pytest.approx(math.log(nominal), rel=1e-12)
    assert math.exp(NOMINAL.start_log_density(start) - proposal.log_pdf(start)) <= 1 / 0.2  # defensive bound
    assert NOMINAL.start_log_density({"sun_altitude_angle": -1.0, BEARING: 0.0}) == -math.inf


def test_the_step_actions_do_not_depend_on_the_proposal() -> None:
    _, crude_rows = toy_estimate(3, method="crude", episodes=40)
    _, is_rows = toy_estimate(3, episodes=40)
    # the same (seed, index) gives the same scene, episode seed and step-action stream under any proposal
    assert [(r["scene"], r["episode_seed"]) for r in crude_rows] == [(r["scene"], r["episode_seed"]) for r in is_rows]


def test_degenerate_weights_raise_the_warning() -> None:
    failed = [True, True] + [False] * 98
    est = estimator.importance(failed, [8.0, 0.0] + [-30.0] * 98)
    assert any("degenerate" in w for w in est.warnings)
    assert any("one failure carries" in w for w in est.warnings)
    healthy = estimator.importance(failed, [0.0] * 100)
    assert not healthy.warnings and healthy.probability == pytest.approx(0.02)


def test_the_same_seed_gives_the_same_estimate() -> None:
    a, rows_a = toy_estimate(5, episodes=60)
    b, rows_b = toy_estimate(5, episodes=60)
    c, _ = toy_estimate(6, episodes=60)
    assert rows_a == rows_b and a == b
    assert c.probability != a.probability or c.ess != a.ess


def test_summary_splits_the_estimate_over_failure_clusters() -> None:
    est, rows = toy_estimate(1)
    spec = EstimateSpec(member="glare_blind", method="importance", episodes=120, seed=1)
    s = summarise(spec, rows, NOMINAL, 12.8, [])
    assert s["estimate"]["probability"] == pytest.approx(est.probability)
    assert s["clusters"][0]["cluster"] == "toy" and s["clusters"][0]["share"] == 1.0
    assert s["per_hour"] == pytest.approx(est.probability * 3600 / 12.8)
    assert s["crude_episodes_for_0.3"] > 2000 and s["episodes_spent"] == 120 and s["estimate"]["episodes"] == 60


def test_elite_takes_every_failure_else_the_top_share() -> None:
    assert elite([0.1, 0.9, 0.5, 0.2, 0.3], [False] * 5, 0.2) == [1]
    assert sorted(elite([0.1, 0.9, 0.5, 0.2, 0.3], [True, False, False, True, False], 0.2)) == [0, 3]


def test_nominal_files_are_checked(tmp_path: Path) -> None:
    f = tmp_path / "n.toml"
    f.write_text("[start.sun_altitude_angle]\nlow = 0\nhigh = 20\n[start.sun_bearing]\nlow = -180\nhigh = 180\n")
    starts = check_starts(load_starts(f), ("sun_altitude_angle", "sun_azimuth_angle"))
    assert [(r.name, r.low, r.high) for r in starts] == [("sun_altitude_angle", 0, 20), (BEARING, -180, 180)]
    with pytest.raises(UserInputError, match="needs every held knob"):
        check_starts(starts, ("sun_altitude_angle",))  # the bearing is no knob this member turns
    f.write_text("[start.sun_altitude_angle]\nlow = 0\nhigh = 20\n[start.sun_bearing]\nlow = -180\nhigh = 180\n"
                 "[start.fog_density]\nlow = 0\nhigh = 10\n")
    held = ("sun_altitude_angle", "sun_azimuth_angle")
    with_fog = check_starts(load_starts(f), held, ("fog_density", *held))  # a climatological fog start
    assert [r.name for r in with_fog] == ["sun_altitude_angle", BEARING, "fog_density"]
    with pytest.raises(UserInputError, match="may add knobs it turns"):
        check_starts(load_starts(f), held, held)
    f.write_text("[start.sun_altitude_angle]\nlow = 0\nhigh = 200\n")
    with pytest.raises(UserInputError, match="leaves the allowed"):
        load_starts(f)
    f.write_text("[start.fog]\nlow = 0\nhigh = 2\n")
    with pytest.raises(UserInputError, match="not a knob"):
        load_starts(f)
    with pytest.raises(UserInputError, match="low < high"):
        StartRange("x", 3.0, 3.0)


def test_spec_refuses_bad_values_naming_the_flag() -> None:
    for kwargs, flag in (({"method": "mcmc"}, "--method"), ({"defensive": 0.0}, "--defensive"),
                         ({"stages": 0}, "--stages"), ({"episodes": 0}, "--episodes"), ({"elite": 1.5}, "--elite"),
                         ({"steps": 0}, "--steps"), ({"estimate_from": "all"}, "--estimate-from")):
        with pytest.raises(UserInputError, match=flag):
            EstimateSpec(**{"member": "low_sun", "method": "importance", "episodes": 10, **kwargs})


def test_default_nominal_is_what_each_odd_allows() -> None:
    from genesis_rl.core.config import from_mapping
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
    from genesis_rl.estimation.nominal import default_starts
    from genesis_rl.sut.zoo.members import env_settings, zoo_member

    expected = {"glare_blind": (-90.0, 90.0), "low_sun": (0.0, 90.0), "builtin_highway": (15.0, 90.0)}
    for name, (lo, hi) in expected.items():
        env = GenesisEnv(from_mapping(EnvConfig, {**env_settings(zoo_member(name)), "scenes": 2,
                                                  "observation": "features"}, "env"))
        try:
            starts = default_starts(env.held_knobs, env.odd, env.start_weather, env.conditions_model)
        finally:
            env.close()
        assert [(r.name, round(r.low, 6), r.high) for r in starts] == [("sun_altitude_angle", lo, hi),
                                                                        (BEARING, -180.0, 180.0)]


def test_estimate_command_refuses_bad_input_with_exit_2(tmp_path: Path, capsys) -> None:
    from genesis_rl.commands.cli import main

    assert main(["estimate", "--member", "nobody", "--out", str(tmp_path / "o")]) == 2
    assert "nobody" in capsys.readouterr().err
    assert main(["estimate", "--member", "low_sun", "--defensive", "0", "--out", str(tmp_path / "o")]) == 2
    assert "--defensive" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.xdist_group("estimate")
def test_a_real_estimate_is_the_same_with_one_or_two_workers_and_resumes(tmp_path: Path) -> None:
    from genesis_rl.commands.cli import main

    args = ["estimate", "--member", "glare_blind", "--episodes", "4", "--stages", "2", "--steps", "12", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    assert main([*args, "--workers", "2", "--out", str(tmp_path / "two")]) == 0
    one, two = ((tmp_path / d / "episodes.csv").read_text() for d in ("one", "two"))
    assert one == two and len(one.splitlines()) == 5
    assert main([*args, "--out", str(tmp_path / "one")]) == 2  # written: --resume or --force
    assert main([*args, "--out", str(tmp_path / "one"), "--resume"]) == 0
    assert (tmp_path / "one" / "episodes.csv").read_text() == one
    assert (tmp_path / "one" / "estimate.png").stat().st_size > 10_000
    # a typo in --tilt is refused before --force replaces anything: the estimate there stays as it was
    before = {p.name: p.read_bytes() for p in (tmp_path / "one").iterdir()}
    assert main([*args, "--tilt", "sun_altitude", "--force", "--out", str(tmp_path / "one")]) == 2
    assert {p.name: p.read_bytes() for p in (tmp_path / "one").iterdir()} == before


@pytest.mark.xdist_group("estimate")
def test_a_resumed_estimate_may_read_its_episodes_from_other_stages(tmp_path: Path) -> None:
    """--estimate-from only reads the episodes: a resumed estimate may change it and plays nothing again; a
    setting that decides the episodes may not change."""
    import json

    from genesis_rl.commands.cli import main

    args = ["estimate", "--member", "glare_blind", "--episodes", "4", "--stages", "3", "--steps", "12", "--quiet",
            "--out", str(tmp_path)]
    assert main(args) == 0
    played = (tmp_path / "episodes.csv").read_text()
    last = json.loads((tmp_path / "estimate.json").read_text())
    assert last["spec"]["estimate_from"] == "last" and last["estimate"]["episodes"] == 2  # stages of 1, 1, 2
    assert main([*args, "--resume", "--estimate-from", "adapted"]) == 0
    adapted = json.loads((tmp_path / "estimate.json").read_text())
    assert (tmp_path / "episodes.csv").read_text() == played
    assert adapted["spec"]["estimate_from"] == "adapted" and adapted["estimate"]["episodes"] == 3  # stages 1 and 2
    assert adapted["episodes_spent"] == 4
    assert main([*args, "--resume", "--defensive", "0.3"]) == 2


@pytest.mark.xdist_group("estimate")
def test_crude_monte_carlo_goes_on_to_more_episodes_with_resume(tmp_path: Path) -> None:
    import json

    from genesis_rl.commands.cli import main

    args = ["estimate", "--member", "low_sun", "--method", "crude", "--steps", "8", "--quiet", "--out", str(tmp_path)]
    assert main([*args, "--episodes", "2"]) == 0
    first = (tmp_path / "episodes.csv").read_text().splitlines()
    written = json.loads((tmp_path / "estimate.json").read_text())
    for field in ("pilot", "elite_min", "smoothing", "tilt"):  # as an estimate started before they existed: crude
        del written["spec"][field]  # Monte Carlo does not use them, so it resumes whatever they read as
    (tmp_path / "estimate.json").write_text(json.dumps(written))
    assert main([*args, "--episodes", "3", "--resume"]) == 0
    more = (tmp_path / "episodes.csv").read_text().splitlines()
    assert more[:3] == first and len(more) == 4  # the first two kept as they were, one more played
    assert json.loads((tmp_path / "estimate.json").read_text())["estimate"]["episodes"] == 3
    assert main([*args, "--episodes", "3", "--resume", "--stages", "2", "--method", "importance"]) == 2
    (tmp_path / "estimate.json").write_text("[1, 2]")  # a damaged file: refused, no traceback
    assert main([*args, "--episodes", "3", "--resume"]) == 2


# -- the lead's braking event (members that turn lead_decel) -----------------------------------------------------

def test_the_braking_events_exponential_by_hand_and_by_sampling() -> None:
    from genesis_rl.estimation.nominal import BRAKE_DECEL

    decel = StartRange(BRAKE_DECEL, 0.0, 6.0, mean=0.6)
    # the truncated exponential's density by hand, and that it integrates to one
    by_hand = (1 / 0.6) * math.exp(-3.0 / 0.6) / (1 - math.exp(-6.0 / 0.6))
    assert math.exp(decel.log_density(3.0)) == pytest.approx(by_hand, rel=1e-12)
    xs = np.linspace(0.0, 6.0, 60_001)
    assert np.trapezoid(np.exp([decel.log_density(float(x)) for x in xs]), xs) == pytest.approx(1.0, abs=1e-6)
    assert decel.log_density(6.01) == -math.inf and decel.log_density(-0.01) == -math.inf
    # sampling follows it: 1 in about 150 brakes at 3 m/s^2 or harder
    rng = np.random.default_rng(0)
    draws = np.array([decel.sample(rng) for _ in range(200_000)])
    assert draws.min() >= 0.0 and draws.max() <= 6.0
    assert draws.mean() == pytest.approx(0.6, rel=0.01)
    assert (draws >= 3.0).mean() == pytest.approx(math.exp(-5) - math.exp(-10), rel=0.1)


def test_a_braking_events_likelihood_ratio_by_hand() -> None:
    from genesis_rl.estimation.nominal import BRAKE_DECEL, BRAKE_ONSET

    onset, decel = StartRange(BRAKE_ONSET, 0.0, 12.8), StartRange(BRAKE_DECEL, 0.0, 6.0, mean=0.6)
    nominal = NominalModel((ALT, onset, decel), action_dim=6)
    proposal = StartProposal(nominal, (TruncatedNormal(ALT, 45.0, 45.0), TruncatedNormal(onset, 2.0, 2.0),
                                       TruncatedNormal(decel, 4.0, 1.0)), 0.2)
    start = {"sun_altitude_angle": 30.0, BRAKE_ONSET: 1.0, BRAKE_DECEL: 4.5}
    n = NormalDist()
    p = (1 / 90) * (1 / 12.8) * (1 / 0.6) * math.exp(-4.5 / 0.6) / (1 - math.exp(-10))
    normals = (n.pdf(-15 / 45) / 45 / (n.cdf(1) - n.cdf(-1))) * (n.pdf(-0.5) / 2 / (n.cdf(5.4) - n.cdf(-1))) * \
        (n.pdf(0.5) / (n.cdf(2) - n.cdf(-4)))
    q = 0.2 * p + 0.8 * normals
    assert nominal.start_log_density(start) == pytest.approx(math.log(p), rel=1e-12)
    assert proposal.log_pdf(start) == pytest.approx(math.log(q), rel=1e-12)
    # a hard braking is rare under the nominal model: its weight is far below one where the proposal sits
    assert math.exp(nominal.start_log_density(start) - proposal.log_pdf(start)) < 0.01


def test_braking_event_files_are_checked(tmp_path: Path) -> None:
    from genesis_rl.estimation.nominal import BRAKE_DECEL, BRAKE_ONSET

    held, turned = ("sun_altitude_angle", "sun_azimuth_angle"), ("fog_density", "lead_decel",
                                                                 "sun_altitude_angle", "sun_azimuth_angle")
    base = "[start.sun_altitude_angle]\nlow = 15\nhigh = 90\n[start.sun_bearing]\nlow = -180\nhigh = 180\n"
    f = tmp_path / "n.toml"
    f.write_text(base + f"[start.{BRAKE_ONSET}]\nlow = 0\nhigh = 10\n"
                        f"[start.{BRAKE_DECEL}]\nlow = 0\nhigh = 6\nmean = 1.2\n")
    starts = check_starts(load_starts(f), held, turned)
    assert [(r.name, r.mean) for r in starts][2:] == [(BRAKE_ONSET, None), (BRAKE_DECEL, 1.2)]
    with pytest.raises(UserInputError, match="the braking event"):
        check_starts(load_starts(f), held, ("fog_density", *held))  # no lead_decel: no braking event
    f.write_text(base + f"[start.{BRAKE_DECEL}]\nlow = 0\nhigh = 6\n")
    with pytest.raises(UserInputError, match="both"):
        check_starts(load_starts(f), held, turned)  # an onset is needed too
    f.write_text(base + f"[start.{BRAKE_DECEL}]\nlow = 0\nhigh = 6\nmean = -1\n")
    with pytest.raises(UserInputError, match="mean = -1"):
        load_starts(f)
    f.write_text(base + f"[start.{BRAKE_DECEL}]\nlow = 0\nhigh = 9\n")
    with pytest.raises(UserInputError, match="leaves the allowed"):
        load_starts(f)


@pytest.mark.xdist_group("estimate")
def test_the_lead_brakes_as_the_drawn_event_says() -> None:
    """latency_braking's default nominal model draws the lead's braking at the start; played, the knob holds 0
    until the onset, then rises at its natural rate (4 m/s^2 a second) to the drawn deceleration."""
    from genesis_rl.core.config import from_mapping
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
    from genesis_rl.estimation.episodes import EpisodeTask, play
    from genesis_rl.estimation.nominal import BRAKE_DECEL, BRAKE_ONSET
    from genesis_rl.estimation.run import nominal_model
    from genesis_rl.sut.zoo.members import env_settings, zoo_member

    env = GenesisEnv(from_mapping(EnvConfig, {**env_settings(zoo_member("latency_braking")), "scenes": 2,
                                              "observation": "features", "episode_steps": 40}, "env"))
    try:
        nominal = nominal_model(EstimateSpec("latency_braking", "crude", 1, steps=40, stages=1), env)
        by_name = {r.name: r for r in nominal.starts}
        assert (by_name[BRAKE_ONSET].low, by_name[BRAKE_ONSET].high) == (0.0, pytest.approx(2.0))
        assert (by_name[BRAKE_DECEL].high, by_name[BRAKE_DECEL].mean) == (6.0, 0.6)  # the ODD's strongest
        start = {"sun_altitude_angle": 60.0, BEARING: 0.0, BRAKE_ONSET: 0.5, BRAKE_DECEL: 1.3}
        play(env, EpisodeTask(0, 0, 7, (0, 0, 2), start), 40)
        decel = [r.knobs["lead_decel"] for r in env.records]
    finally:
        env.close()
    onset_step = round(0.5 / 0.05) - 1  # the first step whose end reaches the onset
    assert decel[:onset_step] == [0.0] * onset_step
    assert decel[onset_step:onset_step + 7] == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.3])
    assert decel[-1] == pytest.approx(1.3)


def test_a_tilt_of_some_variables_leaves_the_rest_nominal_and_the_ratio_exact() -> None:
    proposal = StartProposal.broad(NOMINAL, 0.2, tilt=("sun_altitude_angle",))
    assert [n.range.name for n in proposal.normals] == ["sun_altitude_angle"]
    start = {"sun_altitude_angle": 7.0, BEARING: 100.0}
    n = NormalDist()
    alt = n.pdf((7 - 45) / 45) / 45 / (n.cdf(1) - n.cdf(-1))
    q = 0.2 / (90 * 360) + 0.8 * alt / 360  # the bearing keeps its nominal density in both components
    assert proposal.log_pdf(start) == pytest.approx(math.log(q), rel=1e-12)
    # the untilted bearing is drawn uniformly whatever the normals say
    narrow = StartProposal(NOMINAL, (TruncatedNormal(ALT, 5.0, 1.0),), 0.0)
    rng = np.random.default_rng(0)
    draws = [narrow.sample(rng) for _ in range(4000)]
    assert list(draws[0]) == ["sun_altitude_angle", BEARING]
    assert np.mean([d["sun_altitude_angle"] for d in draws]) == pytest.approx(5.0, abs=0.1)
    bearings = np.array([d[BEARING] for d in draws])
    assert bearings.min() < -170 and bearings.max() > 170 and abs(bearings.mean()) < 10
    # a refit moves only the tilted normal, smoothed toward the one before when asked
    refit = proposal.refit([{"sun_altitude_angle": 5.0, BEARING: 0.0}, {"sun_altitude_angle": 7.0, BEARING: 9.0}],
                           [1.0, 1.0], smoothing=0.5)
    (only,) = refit.normals
    assert (only.mean, only.spread) == (pytest.approx(0.5 * 6.0 + 0.5 * 45.0), pytest.approx(0.5 * 4.5 + 0.5 * 45.0))


def test_the_elite_is_never_fewer_than_its_least() -> None:
    scores, failed = [0.1, 0.9, 0.5, 0.3, 0.7, 0.2, 0.8, 0.4, 0.6, 0.0], [False] * 10
    assert elite(scores, failed, 0.2) == [1, 6]  # two of ten: a normal fit to two episodes
    assert elite(scores, failed, 0.2, least=5) == [1, 6, 4, 8, 2]
    with pytest.raises(UserInputError, match="--elite-min"):
        EstimateSpec("low_sun", "importance", 10, elite_min=0)
    with pytest.raises(UserInputError, match="--smoothing"):
        EstimateSpec("low_sun", "importance", 10, smoothing=0.0)


def test_danger_is_the_largest_inverse_time_to_collision() -> None:
    from types import SimpleNamespace

    from genesis_rl.estimation.episodes import DANGER_CAP, danger

    def step(ego: float, gap: float, lead: float, collided: bool = False, present: bool = True):
        return SimpleNamespace(ego=SimpleNamespace(speed=ego), collision=SimpleNamespace(collided=collided),
                               lead=SimpleNamespace(present=present, true_distance=gap, speed=lead))

    # closing at 5 m/s on 20 m, then at 8 m/s on 10 m: 0.8 a second; an opening gap and no lead count nothing
    assert danger([step(20, 20, 15), step(18, 10, 10), step(10, 5, 12), step(30, float("nan"), float("nan"),
                                                                         present=False)]) == pytest.approx(0.8)
    assert danger([step(10, 30, 12)]) == 0.0
    assert danger([step(10, 30, 9), step(9, 0.0, 0.0, collided=True)]) == DANGER_CAP
    assert danger([step(10, 0.01, 0.0)]) == DANGER_CAP  # a gap of a centimetre closing at 10 m/s: capped



def test_importance_sampling_is_unbiased_where_a_rare_braking_decides_the_failure() -> None:
    """A toy shaped like latency_braking (docs/estimation.md's table): it fails, with probability 3/4, when the
    lead brakes at 2.5 m/s^2 or harder within the first 6 s; the braking is the nominal exponential (mean 0.6),
    so the closed form is 0.75 P(decel >= 2.5) 6 / 12.8 = 0.0054. The proposal tilts the event alone, as
    `--tilt lead_brake_onset_s,lead_brake_decel --smoothing 0.7` does; 80 episodes, 3 stages, pilot 0.4, the
    estimate from both adapted stages (`--estimate-from adapted`), against the last stage alone."""
    from genesis_rl.estimation.nominal import BRAKE_DECEL, BRAKE_ONSET

    onset, decel = StartRange(BRAKE_ONSET, 0.0, 12.8), StartRange(BRAKE_DECEL, 0.0, 6.0, mean=0.6)
    nominal = NominalModel((StartRange("sun_altitude_angle", 15.0, 90.0), BEAR, onset, decel), action_dim=3)
    truth = 0.75 * (math.exp(-2.5 / 0.6) - math.exp(-10.0)) / -math.expm1(-10.0) * 6 / 12.8

    def play(tasks):
        for t in tasks:
            coin = np.random.default_rng(list(t.action_seed)).uniform() < 0.75
            failed = bool(t.start[BRAKE_DECEL] >= 2.5 and t.start[BRAKE_ONSET] <= 6.0 and coin)
            danger = t.start[BRAKE_DECEL] / 6.0 - t.start[BRAKE_ONSET] / 12.8
            yield toy_row(t, failed, danger, "braking")

    values, covered, last_only = [], 0, []
    for seed in range(60):
        spec = EstimateSpec(member="latency_braking", method="importance", episodes=80, seed=seed, stages=3,
                            pilot=0.4, smoothing=0.7, tilt=(BRAKE_ONSET, BRAKE_DECEL), estimate_from="adapted")
        rows: list = []
        play_stages(spec, nominal, 50, rows, play)
        assert spec.estimate_stages == (1, 2)  # the adapted stages: all but the broad first pilot
        used = [r for r in rows if r["stage"] in spec.estimate_stages]
        est = estimator.importance([r["failed"] for r in used], [r["log_weight"] for r in used])
        values.append(est.probability)
        covered += est.ci95[0] <= truth <= est.ci95[1]
        last = [r for r in rows if r["stage"] == 2]
        last_only.append(estimator.importance([r["failed"] for r in last], [r["log_weight"] for r in last]).probability)
    mean, sd = float(np.mean(values)), float(np.std(values, ddof=1))
    # unbiased: the mean of 60 runs within 3 standard errors (about 12 % of the truth here)
    assert abs(mean - truth) < 3 * sd / math.sqrt(60), (mean, truth, sd)
    # and concentrated: crude Monte Carlo needs (1 - p) / p = 183 episodes per unit of relative variance, these
    # 80-episode runs spend under 80 (sd / p)^2 < 12 (measured 0.316 over 300 seeds: about 23x fewer episodes)
    assert 80 * (sd / truth) ** 2 < 12, sd / truth
    # pooling the adapted pilot stage with the last one beats the last one alone (0.351 over 300 seeds: 18.6x)
    assert sd < float(np.std(last_only, ddof=1)), (sd, float(np.std(last_only, ddof=1)))
    assert covered >= 47, covered  # the normal interval is optimistic on heavy-tailed weights: 89 % over 300 seeds
