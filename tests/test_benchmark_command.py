"""``genesis-rl benchmark`` (issue 33): the matrix runs end to end, its figures are the per-campaign metrics
pooled, an interrupted benchmark resumes to the same leaderboard, and bad input is refused naming the field;
the rank statistics are checked by hand."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from builders import tiny_run

from genesis_rl.benchmark.matrix import BenchmarkSpec, campaign_folder, run_benchmark
from genesis_rl.benchmark.metrics import falsifier_metrics
from genesis_rl.benchmark.ranks import chi2_sf, compare_ranks, rank_rows
from genesis_rl.benchmark.reproduce import reproduction_file
from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.zoo import members as zoo
from genesis_rl.sut.zoo.members import ZooMember
from genesis_rl.sut.zoo.trigger import Bound, TriggerRegion

#: a test-only weakness whose failures are certain: a system that never sees anything, in clear highway air
BLIND = ZooMember(name="blind_highway", kind="weakness", summary="test only: the blind system", system="blind",
                  odd="highway_day.toml", map="highway", trigger=TriggerRegion((Bound("visibility_m", 2000.0),)),
                  env={"dynamics": "natural"})


def test_chi_square_tail_matches_the_tables():
    assert chi2_sf(3.841, 1) == pytest.approx(0.05, abs=2e-4)
    assert chi2_sf(5.991, 2) == pytest.approx(0.05, abs=2e-4)
    assert chi2_sf(7.815, 3) == pytest.approx(0.05, abs=2e-4)
    assert chi2_sf(13.277, 4) == pytest.approx(0.01, abs=1e-4)
    assert chi2_sf(0.0, 3) == 1.0


def test_ranks_friedman_and_critical_difference_by_hand():
    assert rank_rows({"a": 0.9, "b": 0.5, "c": 0.5}) == {"a": 1.0, "b": 2.5, "c": 2.5}
    # three systems on which a always beats b, and b beats c: average ranks 1, 2, 3; Friedman chi2 =
    # 12 N / (k (k + 1)) * sum(R^2) - 3 N (k + 1) = 12 * 3 / 12 * 14 - 36 = 6, p = exp(-3) with 2 dof
    table = {s: {"a": 0.9, "b": 0.5, "c": 0.1} for s in ("x", "y", "z")}
    r = compare_ranks(table, ("a", "b", "c"))
    assert r["average_rank"] == {"a": 1.0, "b": 2.0, "c": 3.0}
    assert r["friedman_chi2"] == pytest.approx(6.0) and r["friedman_p"] == pytest.approx(0.049787, abs=1e-6)
    assert r["critical_difference"] == pytest.approx(2.343 * (3 * 4 / 18) ** 0.5, abs=1e-4)
    assert compare_ranks({"x": {"a": 1.0, "b": 0.0}}, ("a", "b"))["friedman_p"] is None  # one system: no test


def test_bad_benchmark_input_is_refused_naming_the_field(tmp_path):
    with pytest.raises(UserInputError, match=r"benchmark members: \['nope'\] unknown; allowed: low_sun"):
        BenchmarkSpec(members=("nope",), policies=("sunny",))
    with pytest.raises(UserInputError, match=r"benchmark policies: \['agent'\] unknown.*one training per member"):
        BenchmarkSpec(members=("low_sun",), policies=("agent",))
    with pytest.raises(UserInputError, match="benchmark trials = 0"):
        BenchmarkSpec(members=("low_sun",), policies=("sunny",), trials=0)
    assert main(["benchmark", "--out", str(tmp_path / "b"), "--policies", "sunny,,random"]) == 2
    assert main(["benchmark", "--out", str(tmp_path / "b"), "--trials", "0"]) == 2
    assert not (tmp_path / "b").exists()  # refused before anything was written
    assert main(["benchmark", "--list"]) == 0
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / "benchmark.json").write_text("{not json")
    with pytest.raises(UserInputError, match="benchmark.json .* is not valid JSON"):
        run_benchmark(BenchmarkSpec(members=("low_sun",), policies=("sunny",)), damaged, resume=True, progress=False)
    (damaged / "benchmark.json").write_text("[1, 2]")
    with pytest.raises(UserInputError, match="holds no benchmark spec"):
        run_benchmark(BenchmarkSpec(members=("low_sun",), policies=("sunny",)), damaged, resume=True, progress=False)


@pytest.fixture(scope="session")
def _blind_benchmark_built(tmp_path_factory) -> tuple[BenchmarkSpec, Path]:
    """blind_highway (a weakness) and oracle_highway (a control), sunny and random, 2 trials of 2 scenes: built
    once a session (the tests copy what they change)."""
    zoo.ZOO[BLIND.name] = BLIND
    try:  # the registry is shared by the worker's other tests: never leave the test member in it
        spec = BenchmarkSpec(members=("blind_highway", "oracle_highway"), policies=("sunny", "random"), trials=2,
                             scenes=2, steps=120, reruns=2)
        out = tmp_path_factory.mktemp("bench") / "b"
        run_benchmark(spec, out, progress=False)
        return spec, out
    finally:
        zoo.ZOO.pop(BLIND.name, None)


@pytest.fixture
def blind_benchmark(_blind_benchmark_built, monkeypatch) -> Iterator[tuple[BenchmarkSpec, Path]]:
    """The built benchmark, with its test member in the zoo for this test only."""
    monkeypatch.setitem(zoo.ZOO, BLIND.name, BLIND)
    yield _blind_benchmark_built


def test_the_leaderboard_pools_the_campaigns_metrics(blind_benchmark):
    spec, out = blind_benchmark
    board = json.loads((out / "leaderboard.json").read_text())
    assert (out / "leaderboard.html").read_text().count("<table>") == 2
    for policy in spec.policies:
        per_trial = [falsifier_metrics(campaign_folder(out, "blind_highway", t), BLIND)[policy] for t in range(2)]
        cell = board["cells"]["blind_highway"][policy]
        assert cell["episodes"] == 4 and cell["trials"] == 2
        assert cell["falsified"] == sum(m.falsified for m in per_trial)
        assert cell["falsification_rate_per_trial"] == [m.falsification_rate for m in per_trial]
        assert cell["triggered"] == sum(m.triggered for m in per_trial) <= cell["falsified"]
        assert cell["avoidable"] == sum(t.avoidable for m in per_trial for t in m.trials) <= cell["falsified"]
        assert cell["budget_steps"] == 120
        control = board["cells"]["oracle_highway"][policy]
        assert control["false_alarm_candidates"] == control["falsified"]
    # the blind system crashes in clear air whatever the weather: sunny falsifies it in some trial, and the crash
    # reproduces in worlds no adversary saw (fresh traffic and sensor noise)
    blind = board["cells"]["blind_highway"]["sunny"]
    assert blind["falsified"] >= 1 and blind["reproduction_rate"] >= 0.5
    assert blind["confirmed"] == blind["reproducible"] == blind["triggered"] >= 1
    for member in spec.members:
        for t in range(2):
            again = json.loads(reproduction_file(out, member, campaign_folder(out, member, t)).read_text())
            for policy, scenes in again["policies"].items():
                row_seeds = {s: json.loads((campaign_folder(out, member, t) / "episodes" / policy /
                                            f"scene_{int(s):04d}.json").read_text())["episode_seed"] for s in scenes}
                for scene, entry in scenes.items():  # each reported failure re-run twice, in worlds of its own
                    assert entry["reruns"] == len(entry["runs"]) == 2
                    assert all(r["world_seed"] != row_seeds[scene] for r in entry["runs"])
                    assert entry["reproduced"] == sum(r["reproduced"] for r in entry["runs"])
        for policy in spec.policies:
            cell = board["cells"][member][policy]
            assert cell["confirmed"] <= cell["reported_failures"] <= cell["episodes"]
    assert board["ranks"]["systems"] == ["blind_highway"]


def test_an_interrupted_benchmark_resumes_to_the_same_leaderboard(blind_benchmark, tmp_path):
    spec, out = blind_benchmark
    cut = tmp_path / "cut"
    shutil.copytree(out, cut)
    shutil.rmtree(campaign_folder(cut, "oracle_highway", 1))  # never started
    half = campaign_folder(cut, "blind_highway", 1)  # stopped after its first episodes
    (half / "summary.json").unlink()
    for row in sorted((half / "episodes" / "random").glob("*.json")):
        row.unlink()
    (cut / "leaderboard.json").unlink()
    with pytest.raises(UserInputError, match="exists; pass --resume to continue it or --force"):
        run_benchmark(spec, cut, progress=False)
    with pytest.raises(UserInputError, match="was started with trials = 2, not 3"):
        run_benchmark(BenchmarkSpec(**{**spec.to_json(), "members": spec.members, "policies": spec.policies,
                                       "trials": 3}), cut, resume=True, progress=False)
    run_benchmark(spec, cut, resume=True, progress=False)

    def figures(folder: Path) -> dict:
        return json.loads((folder / "leaderboard.json").read_text())

    assert figures(cut) == figures(out)


def test_campaigns_side_by_side_give_the_same_leaderboard(blind_benchmark, tmp_path):
    """--parallel campaigns: each campaign in a process of its own, two at a time, to the same figures."""
    from genesis_rl.benchmark.matrix import parallel_mode

    spec, out = blind_benchmark
    run_benchmark(spec, tmp_path / "side", workers=2, parallel="campaigns", progress=False)

    def figures(folder: Path) -> dict:
        return json.loads((folder / "leaderboard.json").read_text())

    assert figures(tmp_path / "side") == figures(out)
    assert parallel_mode("auto", 2, None, 4) == "campaigns" and parallel_mode("auto", 2, None, 3) == "episodes"
    assert parallel_mode("auto", 1, None, 8) == "episodes" and parallel_mode("auto", 2, object(), 8) == "campaigns"
    # one Ray worker takes campaigns too: Ray and its actor start once for the matrix, not once a campaign
    assert parallel_mode("auto", 1, object(), 8) == "campaigns"
    assert parallel_mode("episodes", 1, object(), 8) == "episodes"
    with pytest.raises(UserInputError, match="--parallel = 'threads'; allowed: auto, campaigns, episodes"):
        parallel_mode("threads", 2, None, 4)


def test_campaigns_on_ray_actors_resume_to_the_same_leaderboard(blind_benchmark, tmp_path):
    """--executor ray --parallel campaigns: each actor runs whole campaigns in a staging folder and sends the
    files back; a never-started campaign and a half-run one (whose files travel to the actor) end as the local
    run's, and the installed summaries name the benchmark's folder, not the actor's."""
    pytest.importorskip("ray")
    from genesis_rl.distributed.settings import ExecutorSettings

    spec, out = blind_benchmark
    cut = tmp_path / "cut"
    shutil.copytree(out, cut)
    shutil.rmtree(campaign_folder(cut, "oracle_highway", 1))
    half = campaign_folder(cut, "blind_highway", 1)
    (half / "summary.json").unlink()
    kept = sorted((half / "episodes" / "sunny").glob("*.json"))
    for row in sorted((half / "episodes" / "random").glob("*.json")):
        row.unlink()
    import signal

    before = signal.getsignal(signal.SIGTERM)
    run_benchmark(spec, cut, resume=True, workers=2, executor=ExecutorSettings(kind="ray", workers=2),
                  parallel="campaigns", progress=False)
    assert signal.getsignal(signal.SIGTERM) is before  # Ray's own handler does not outlive its session
    assert json.loads((cut / "leaderboard.json").read_text()) == json.loads((out / "leaderboard.json").read_text())
    assert json.loads((half / "summary.json").read_text())["campaign"] == str(half)
    assert [p.read_bytes() for p in kept] == [p.read_bytes() for p in sorted(kept[0].parent.glob("*.json"))]
    assert not [p for p in (cut / "campaigns").rglob(".*") if p.suffix in (".incoming", ".replaced")]
    assert json.loads((half / "run_time.json").read_text())["executor"] == "ray (a campaign per actor)"


def test_a_campaign_process_that_cannot_start_raises_instead_of_hanging():
    """A plug-in that does not import in the spawned process is raised by its first campaign (a pool whose
    initializer raises would start new processes forever)."""
    from genesis_rl.benchmark import parallel
    from genesis_rl.distributed.spawn_pool import SpawnPool

    with SpawnPool(2, parallel._init, (("genesis_rl_no_such_plugin_module",),)) as pool, \
            pytest.raises(UserInputError, match="genesis_rl_no_such_plugin_module"):
        list(pool.imap_unordered(parallel._run, [({}, "unused")]))


def test_under_natural_dynamics_the_sun_is_held_and_only_the_start_sets_it(tmp_path):
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
    from genesis_rl.sut.zoo.members import zoo_member

    low_sun = zoo_member("low_sun")
    env = GenesisEnv(EnvConfig(map="urban", scenes=4, dynamics="natural", odd=str(low_sun.odd_path),
                               episode_steps=256))
    try:
        assert env.held_knobs == ("sun_altitude_angle", "sun_azimuth_angle")
        # the lowest sun the day ODD allows, from a position below the horizon: on the ODD's boundary
        low = env.start_from([0.0, 0.5])
        assert -1.0 <= low["sun_altitude_angle"] <= 1.0 and low["sun_azimuth_angle"] == pytest.approx(180.0)
        assert env.odd.contains(env.conditions_model.conditions(low, None), low)
        draws = [env.natural_start(np.random.default_rng([7, i])) for i in range(40)]
        assert all(env.odd.contains(env.conditions_model.conditions(w, None), w) for w in draws)
        altitudes = [w["sun_altitude_angle"] for w in draws]
        assert min(altitudes) >= 0.0 and max(altitudes) <= 90.0 and np.std(altitudes) > 15.0  # spread, inside
        assert env.natural_start(np.random.default_rng([7, 0])).values == draws[0].values  # seeded
        with pytest.raises(UserInputError, match="the held knobs are"):
            env.start_from([0.5])
    finally:
        env.close()
    paper = GenesisEnv(EnvConfig(map="urban", scenes=4, dynamics="paper", episode_steps=64))
    try:
        assert paper.held_knobs == ()  # 5 % of the range a step: nothing is held
    finally:
        paper.close()


def test_a_natural_start_campaign_records_and_replays_the_start_each_policy_chose(tmp_path):
    from genesis_rl.campaigns.campaign import run_campaign
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.campaigns.records import load_record, replay_record
    from genesis_rl.sut.zoo.members import env_settings, zoo_member

    member = zoo_member("low_sun")
    with pytest.raises(UserInputError, match="campaign option start = 'dawn'; allowed: fixed, natural"):
        CampaignSpec(policies=("random",), map="urban", scenes=1, steps=32, options={"start": "dawn"})
    spec = CampaignSpec(policies=("sunny", "random", "constant"), map="urban", scenes=2, seed=1, steps=40,
                        env=env_settings(member), options={"start": "natural", "constant_action": [-1.0]},
                        records="all")
    run_campaign(spec, tmp_path / "c", progress=False)
    starts = {}
    for path in sorted((tmp_path / "c" / "records").glob("*.json")):
        rec = load_record(path)
        starts.setdefault(rec["policy"], []).append(rec["start_weather"]["sun_altitude_angle"])
        col = rec["knobs"].index("sun_altitude_angle")
        assert abs(rec["schedule"][0][col] - rec["start_weather"]["sun_altitude_angle"]) < 0.01  # held from there
        row = json.loads((tmp_path / "c" / "episodes" / rec["policy"] / f"scene_{rec['scene']['index']:04d}.json")
                         .read_text())
        assert np.isfinite(row["naturalness"]["log_likelihood"])  # the start is no jump in the trajectory
    assert starts["sunny"] == [75.0, 75.0]  # the start weather: sunny does not choose
    assert all(a <= 1.0 for a in starts["constant"])  # -1: as low as the ODD allows
    assert len(set(starts["random"])) == 2 and all(0.0 <= a <= 90.0 for a in starts["random"])
    rec = load_record(next((tmp_path / "c" / "records").glob("random_*.json")))
    assert replay_record(rec, keep_frames=False)["reproduced"]


#: a trained agent for BLIND's env (its system, knobs, dynamics and ODD), trained for a few steps only: the
#: benchmark's plumbing is under test, not the agent
TINY_AGENT = tiny_run(env={"map": "highway", "odd": "{odd}", "dynamics": "natural"}, ppo={"n_epochs": 1},
                      train={"total_timesteps": 32, "seed": 1})


@pytest.mark.render
def test_a_trained_agent_joins_a_finished_benchmark_on_its_own_members_scenes(blind_benchmark, tmp_path):
    """--agent MEMBER=RUN: one campaign a trial on the trial's scenes and seed, under the member's env with what
    the agent observes; --resume adds it to a finished benchmark without changing a figure of the adversaries;
    an agent trained on another system is refused naming the field, before the folder is touched."""
    from genesis_rl.benchmark.matrix import agent_campaign_folder

    spec, out = blind_benchmark
    run = tmp_path / "agent_s1"
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_AGENT.format(odd=zoo.ODD_DIR / BLIND.odd))
    assert main(["train", "--config", str(config), "--out", str(run), "--quiet"]) == 0
    grown = tmp_path / "grown"
    shutil.copytree(out, grown)
    with_agent = BenchmarkSpec(**{**spec.to_json(), "members": spec.members, "policies": spec.policies,
                                  "agents": {"blind_highway": (str(run),)}})
    board = run_benchmark(with_agent, grown, resume=True, progress=False)
    cell = board["cells"]["blind_highway"]["agent:agent_s1"]
    assert (cell["episodes"], cell["trials"], cell["budget_steps"]) == (4, 2, 120)
    assert cell["falsified"] >= 1  # the blind system crashes in clear air whatever the agent does
    before = json.loads((out / "leaderboard.json").read_text())
    assert {p: board["cells"]["blind_highway"][p] for p in spec.policies} == before["cells"]["blind_highway"]
    assert board["ranks"] == before["ranks"]  # an agent is trained per member: it stays out of the rank test
    for trial in range(2):
        agent_meta = json.loads((agent_campaign_folder(grown, "blind_highway", trial, str(run)) / "campaign.json")
                                .read_text())
        adversaries = json.loads((campaign_folder(grown, "blind_highway", trial) / "campaign.json").read_text())
        assert agent_meta["scenes"] == adversaries["scenes"]  # the trial's scenes and episode seeds
        assert agent_meta["spec"]["policies"] == ["agent"] and agent_meta["spec"]["seed"] == trial
        assert (agent_meta["spec"]["env"]["obs_width"], agent_meta["spec"]["env"]["system"]) == (36, "blind")
    assert "agent:agent_s1" in (grown / "leaderboard.html").read_text()
    with pytest.raises(UserInputError, match="has agents .* that --agent leaves out"):
        run_benchmark(spec, grown, resume=True, progress=False)
    elsewhere = BenchmarkSpec(members=("oracle_highway",), policies=("sunny",), trials=1, scenes=1, steps=20,
                              agents={"oracle_highway": (str(run),)})
    with pytest.raises(UserInputError, match="trained with env.system = 'blind'; zoo member 'oracle_highway' has "
                                             "'oracle'"):
        run_benchmark(elsewhere, tmp_path / "elsewhere", progress=False)
    assert not (tmp_path / "elsewhere").exists()
    with pytest.raises(UserInputError, match="member 'low_sun' is not among the members"):
        BenchmarkSpec(members=("oracle_highway",), policies=("sunny",), agents={"low_sun": (str(run),)})
    assert main(["benchmark", "--out", str(tmp_path / "c"), "--members", "oracle_highway", "--agent",
                 "oracle_highway"]) == 2
    from genesis_rl.benchmark.matrix import agent_label  # seeds compared at one checkpoint keep their names apart

    assert agent_label(str(run)) == agent_label(str(run / "agent.zip")) == "agent:agent_s1"
    assert agent_label(str(run / "checkpoints" / "step_00000016.zip")) == "agent:agent_s1/step_00000016"


def test_the_page_shows_a_members_failure_rate_estimate_beside_its_failures(blind_benchmark, tmp_path):
    spec, out = blind_benchmark
    est = tmp_path / "est"
    assert main(["estimate", "--member", "oracle_highway", "--method", "crude", "--episodes", "2", "--steps", "8",
                 "--quiet", "--out", str(est)]) == 0
    copy = tmp_path / "b"
    shutil.copytree(out, copy)
    with pytest.raises(UserInputError, match="is of member 'oracle_highway', not 'blind_highway'"):
        run_benchmark(spec, copy, resume=True, progress=False, estimates={"blind_highway": est})
    with pytest.raises(UserInputError, match="does not play"):
        run_benchmark(spec, copy, resume=True, progress=False, estimates={"low_sun": est})
    board = run_benchmark(spec, copy, resume=True, progress=False, estimates={"oracle_highway": est})
    assert board["estimates"]["oracle_highway"]["estimate"]["episodes"] == 2
    page = (copy / "leaderboard.html").read_text()
    assert page.count("Failure rate under natural conditions: 0 per 0.4 s episode") == 1
    from genesis_rl.analysis.report import build_report

    report = tmp_path / "report.html"
    build_report(campaign_folder(copy, "oracle_highway", 0), report, estimate=est)
    assert "Failure rate under natural conditions: 0 per 0.4 s episode [95 % CI 0, 0.842]" in report.read_text()
    with pytest.raises(UserInputError, match="estimates member 'oracle_highway' .system = 'oracle'.; the campaign "
                                             "has system = "):
        build_report(campaign_folder(copy, "blind_highway", 0), tmp_path / "r2.html", estimate=est)
    kept = (est / "estimate.json").read_text()
    with pytest.raises(UserInputError):  # never onto the estimate it reads, --force or not
        build_report(campaign_folder(copy, "oracle_highway", 0), est / "estimate.json", force=True, estimate=est)
    assert (est / "estimate.json").read_text() == kept


def test_resume_refuses_a_finished_trial_whose_campaign_was_edited(blind_benchmark, tmp_path):
    """An edited spec inside a kept trial (a policy dropped) had been accepted, and the leaderboard silently lost
    the trial; the resumed benchmark now names the file."""
    spec, out = blind_benchmark
    cut = tmp_path / "cut"
    shutil.copytree(out, cut)
    edited = campaign_folder(cut, "blind_highway", 1) / "campaign.json"
    meta = json.loads(edited.read_text())
    meta["spec"]["policies"] = ["sunny"]
    edited.write_text(json.dumps(meta))
    with pytest.raises(UserInputError, match=r"campaign.json' holds other settings than this trial's \(policies\)"):
        run_benchmark(spec, cut, resume=True, progress=False)
