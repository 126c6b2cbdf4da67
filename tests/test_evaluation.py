"""Evaluation campaigns: determinism, resume, failure modes, records and replay, report and export."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.campaigns.campaign import CampaignResult, CampaignSpec, pick_scenes, run_campaign
from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.stats import bootstrap_mean_ci, paired_comparison
from genesis_rl.labels.failure_modes import FailureModeThresholds, classify_timeline

DT = 0.05


# -- failure modes on synthetic timelines ------------------------------------------------------------
def _mode(timeline) -> str:
    return classify_timeline(timeline, DT)["mode"]


def test_never_detected_is_non_detection() -> None:
    assert _mode([False] * 60) == "non_detection"
    assert _mode([False] * 57 + [True] * 3) == "non_detection"  # 5% < 10%


def test_flicker_is_intermittent_detection() -> None:
    assert _mode(([True] * 5 + [False] * 5) * 6) == "intermittent_detection"


def test_seen_only_at_the_end_is_delayed_detection() -> None:
    # 2 s in view and missed, then detected for the last 1 s
    assert _mode([False] * 40 + [True] * 20) == "delayed_detection"
    # the same, but detected 2.5 s before impact: in time
    assert _mode([False] * 40 + [True] * 50) == "detected"


def test_detected_then_lost_before_impact_is_lost_detection() -> None:
    assert _mode([True] * 60 + [False] * 20) == "lost_detection"
    assert _mode([True] * 60 + [False] * 10) == "detected"  # 0.5 s dropout: under min_blind_s


def test_out_of_view_and_detected() -> None:
    assert _mode([None] * 30) == "out_of_view"
    assert _mode([None] * 10 + [True] * 50) == "detected"
    # thresholds are honoured: with min_flips 20 the flicker is no longer intermittent
    th = FailureModeThresholds(min_flips=20)
    assert classify_timeline(([True] * 5 + [False] * 5) * 6, DT, th)["mode"] != "intermittent_detection"


# -- statistics ---------------------------------------------------------------------------------------
def test_bootstrap_ci_brackets_the_mean_and_is_seeded() -> None:
    x = np.random.default_rng(0).normal(3.0, 1.0, 50)
    a, b = bootstrap_mean_ci(x, 1), bootstrap_mean_ci(x, 1)
    assert a == b
    assert a["ci_low"] < a["mean"] < a["ci_high"]
    assert 2.4 < a["ci_low"] and a["ci_high"] < 3.6


def test_paired_comparison_detects_a_shift() -> None:
    base = np.random.default_rng(1).normal(0, 1, 40)
    c = paired_comparison(base + 1.0, base, 0)
    assert c["wins"] == 40 and c["p_value"] < 0.01 and c["difference"]["ci_low"] > 0.9
    same = paired_comparison(base, base, 0)
    assert same["ties"] == 40 and same["p_value"] > 0.5


def test_pick_scenes_is_seeded_and_distinct() -> None:
    a = pick_scenes(100, 10, 3)
    assert a == pick_scenes(100, 10, 3) and a != pick_scenes(100, 10, 4)
    assert len({s for s, _ in a}) == 10
    with pytest.raises(UserInputError, match="--scenes = 101 must be in 1..100"):
        pick_scenes(100, 101, 0)


# -- a tiny campaign ---------------------------------------------------------------------------------
STEPS = 70


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> str:
    from genesis_rl.sim.lite.scenes import generate_catalog

    path = tmp_path_factory.mktemp("cat") / "highway.json"
    generate_catalog("highway", 12, 0).save(path)
    return str(path)


def _spec(catalog: str, **kw) -> CampaignSpec:
    # the blind system never sees a vehicle, so scene 5 (seed 1) ends in a collision at step 49
    base = dict(policies=("sunny", "random"), catalog=catalog, scenes=3, seed=1, steps=STEPS,
                env={"system": "blind"})
    return CampaignSpec(**{**base, **kw})


@pytest.fixture(scope="module")
def campaign(tmp_path_factory, catalog) -> Path:
    folder = tmp_path_factory.mktemp("camp") / "eval"
    run_campaign(_spec(catalog), folder, progress=False)
    return folder


@pytest.fixture(scope="module")
def hit(campaign: Path) -> dict:
    """The random policy's episode with a collision, found from the campaign's rows: the tests that use it
    check behaviour around a collision, whichever scene and step it is (one test pins the golden values)."""
    rows = [json.loads(p.read_text()) for p in sorted((campaign / "episodes" / "random").glob("*.json"))]
    row = next(r for r in rows if r["collision_events"] > 0)
    return {"name": f"scene_{row['scene']:04d}", "step": row["first_collision_step"],
            "record": campaign / row["record"]}


def _stable(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("campaign", "run_seconds", "workers")}


def test_campaign_records_every_episode_and_labels_the_collision(campaign: Path) -> None:
    summary = json.loads((campaign / "summary.json").read_text())
    assert summary["complete"] and summary["scenes"] == 3
    for policy in ("sunny", "random"):
        s = summary["policies"][policy]
        assert s["episodes"] == 3 and s["sim_steps"] == 3 * STEPS
        assert s["episodes_with_collision"] == 1 and s["failure_modes"]["non_detection"] == 1
        assert s["collision"]["mean"] > 0 and s["collision"]["ci_low"] <= s["collision"]["mean"]
    row = json.loads((campaign / "episodes" / "random" / "scene_0005.json").read_text())
    assert row["first_collision_step"] == 49 and row["failure_mode"] == "non_detection"
    assert row["collision"] >= row["collision_speed"] > 3.0  # a_c summed over the steps in contact
    import pyarrow.parquet as pq

    steps = pq.read_table(campaign / "steps" / "random" / "scene_0005.parquet").to_pylist()
    assert len(steps) == STEPS
    knobs = np.array([[r["fog_density"], r["precipitation"]] for r in steps])
    assert np.abs(np.diff(knobs, axis=0)).max() <= 5.0 + 1e-9  # the 5% limit (range 0..100)
    assert {"rule_collision", "rule_proximity", "rule_rss_deficit", "reward", "detections", "gt_boxes"} <= set(steps[0])
    frames = sorted((campaign / "frames" / "random" / "scene_0005").glob("*.jpg"))
    assert frames and int(frames[-1].stem.split("_")[1]) >= 49


def test_same_seed_gives_identical_summary(tmp_path, campaign: Path, catalog: str) -> None:
    again = tmp_path / "again"
    result = run_campaign(_spec(catalog), again, workers=2, progress=False)
    a = json.loads((campaign / "summary.json").read_text())
    b = json.loads((again / "summary.json").read_text())
    assert _stable(a) == _stable(b)
    # the run returns what it wrote, typed, plus how it ran (which summary.json leaves out)
    assert isinstance(result, CampaignResult) and result == {**b, "run_seconds": result.run_seconds,
                                                             "workers": 2, "executor": "local"}
    assert (result.workers, result.executor, result.scenes, result.complete) == (2, "local", 3, True)
    assert result.folder.summary == again / "summary.json" and json.loads(json.dumps(result.to_json())) == result
    random_ = result.policies["random"]
    assert (random_.episodes, random_.episodes_with_collision, random_.failure_modes["non_detection"]) == (3, 1, 1)
    collision = random_.metric("collision")
    assert collision.n == 3 and collision.mean == b["policies"]["random"]["collision"]["mean"] > 0
    with pytest.raises(KeyError, match="'episodes' is not a metric of policy 'random'"):
        random_.metric("episodes")


def test_interrupted_campaign_resumes_without_duplicates(tmp_path, campaign: Path, catalog: str, hit: dict) -> None:
    folder = tmp_path / "resumed"
    shutil.copytree(campaign, folder)
    (folder / "episodes" / "random" / f"{hit['name']}.json").unlink()  # as if killed during that episode
    kept = folder / "episodes" / "sunny" / f"{hit['name']}.json"
    before = kept.stat().st_mtime_ns
    summary = run_campaign(_spec(catalog), folder, resume=True, progress=False)
    assert kept.stat().st_mtime_ns == before  # finished episodes are not redone
    assert json.loads((folder / "run_time.json").read_text())["episodes_run"] == 1
    original = json.loads((campaign / "summary.json").read_text())
    assert summary["policies"] == original["policies"]
    with pytest.raises(UserInputError, match="other settings \\(steps\\)"):
        run_campaign(_spec(catalog, steps=50), folder, resume=True, progress=False)
    with pytest.raises(UserInputError, match="exists; pass --resume"):
        run_campaign(_spec(catalog), folder, progress=False)
    not_a_campaign = tmp_path / "run"
    not_a_campaign.mkdir()
    (not_a_campaign / "agent.zip").write_text("x")
    with pytest.raises(UserInputError, match="not a campaign folder .* refusing to delete it"):
        run_campaign(_spec(catalog), not_a_campaign, force=True, progress=False)
    assert (not_a_campaign / "agent.zip").is_file()


def test_replay_reproduces_the_recorded_violations(tmp_path, campaign: Path, hit: dict) -> None:
    record = hit["record"]
    rc = main(["replay", str(record), "--out", str(tmp_path / "r"), "--quiet"])
    assert rc == 0
    rep = json.loads((tmp_path / "r" / "replay.json").read_text())
    assert rep["reproduced"] and rep["first_collision_step"] == hit["step"]
    assert rep["violations"] == json.loads(record.read_text())["violations"]
    assert (tmp_path / "r" / "replay.gif").stat().st_size > 10_000
    assert main(["replay", str(record), "--out", str(tmp_path / "r"), "--quiet"]) == 2  # no overwrite


def test_a_record_keeps_its_world_seed_and_replays_in_another_world_on_request(tmp_path, campaign: Path,
                                                                             hit: dict) -> None:
    record = json.loads(hit["record"].read_text())
    assert record["world_seed"] == record["episode_seed"]  # a campaign's world is its episode's
    assert main(["replay", str(hit["record"]), "--out", str(tmp_path / "w"), "--quiet", "--no-gif",
                 "--world-seed", "12345"]) == 0
    rep = json.loads((tmp_path / "w" / "replay.json").read_text())
    assert rep["world_seed"] == 12345 and rep["recorded_world_seed"] == record["episode_seed"]
    assert "reproduced" not in rep  # another world is not a reproduction check
    assert rep["violations"] != rep["recorded_violations"]  # the traffic moved otherwise: other figures
    assert main(["replay", str(hit["record"]), "--out", str(tmp_path / "x"), "--world-seed", "-1"]) == 2


def test_replay_says_whether_violations_or_only_the_steps_differ(tmp_path, campaign: Path, hit: dict, capsys) -> None:
    """A record whose step telemetry no longer matches (another renderer, say) but whose violations do is
    not called a different outcome."""
    rec = json.loads((hit["record"]).read_text())
    rec["step_digest"] = "0" * len(rec["step_digest"])
    other = tmp_path / "other_steps.json"
    other.write_text(json.dumps(rec))
    assert main(["replay", str(other), "--out", str(tmp_path / "a"), "--quiet", "--no-gif"]) == 1
    out = capsys.readouterr().out
    assert "violations are the recorded ones, but the per-step telemetry is not" in out
    rec["violations"]["collision"] += 1.0
    other.write_text(json.dumps(rec))
    assert main(["replay", str(other), "--out", str(tmp_path / "b"), "--quiet", "--no-gif"]) == 1
    assert "replayed violations differ from the recorded ones" in capsys.readouterr().out


def test_replay_of_the_builtin_system_is_bit_identical(tmp_path, catalog: str) -> None:
    """The builtin system reads the camera, so this catches renderer or detector state leaking from one
    episode into the next: the second scene's episode is replayed alone in a fresh backend."""
    folder = tmp_path / "builtin"
    spec = _spec(catalog, policies=("random",), scenes=2, steps=40, env={"system": "builtin"}, records="all")
    run_campaign(spec, folder, progress=False)
    second = sorted((folder / "records").glob("*.json"))[-1]
    assert main(["replay", str(second), "--out", str(tmp_path / "r"), "--quiet", "--no-gif"]) == 0
    rep = json.loads((tmp_path / "r" / "replay.json").read_text())
    assert rep["reproduced"] and rep["steps_identical"]


def test_record_of_another_schema_version_is_refused(tmp_path, campaign: Path, hit: dict, capsys) -> None:
    rec = json.loads((hit["record"]).read_text())
    rec["version"] = 99
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(rec))
    assert main(["replay", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "schema version 99" in capsys.readouterr().err


@pytest.mark.parametrize("fmt", ["yolo", "coco"])
def test_export_writes_valid_labels(tmp_path, campaign: Path, fmt: str) -> None:
    out = tmp_path / fmt
    assert main(["export", str(campaign), "--format", fmt, "--out", str(out)]) == 0
    meta = [json.loads(line) for line in (out / "metadata.jsonl").read_text().splitlines()]
    assert len(meta) == len(list((out / "images").glob("*.jpg"))) > 0
    assert all(m["failure_mode"] == "non_detection" and 0 <= m["weather"]["fog_density"] <= 100 for m in meta)
    w, h = 320, 240
    if fmt == "yolo":
        rows = [line.split() for p in (out / "labels").glob("*.txt") for line in p.read_text().splitlines()]
        assert rows
        for cls, cx, cy, bw, bh in rows:
            cx, cy, bw, bh = map(float, (cx, cy, bw, bh))
            assert cls == "0" and 0 <= cx - bw / 2 + 1e-6 and cx + bw / 2 <= 1 + 1e-6
            assert 0 <= cy - bh / 2 + 1e-6 and cy + bh / 2 <= 1 + 1e-6 and bw > 0 and bh > 0
    else:
        coco = json.loads((out / "annotations.json").read_text())
        assert [c["name"] for c in coco["categories"]] == ["vehicle"]
        ids = {im["id"] for im in coco["images"]}
        for a in coco["annotations"]:
            x, y, bw, bh = a["bbox"]
            assert a["image_id"] in ids and a["category_id"] == 1
            assert x >= 0 and y >= 0 and x + bw <= w + 0.01 and y + bh <= h + 0.01 and bw > 0 and bh > 0
    assert main(["export", str(campaign), "--format", fmt, "--out", str(out)]) == 2  # no overwrite


def test_report_builds_and_refuses_to_overwrite(tmp_path, campaign: Path) -> None:
    out = tmp_path / "report.html"
    assert main(["report", str(campaign), "--out", str(out)]) == 0
    text = out.read_text()
    for section in ("Violations by policy", "Failure modes", "Non-detection", "Knob trajectories", "Per scene"):
        assert section in text
    assert text.count("data:image/png;base64") >= 3 and "data:image/jpeg;base64" in text
    # the numbers on the page are the summary's: each policy's row, cell by cell
    summary = json.loads((campaign / "summary.json").read_text())
    for policy, s in summary["policies"].items():
        row = re.search(rf"<tr><td class=l>{policy}</td><td>{s['episodes']}</td>(.*?)</tr>", text)
        assert row, f"no table row for {policy}"
        cells = re.findall(r"<td>(.*?)</td>", row.group(1))
        for metric, cell in zip(("collision", "proximity", "total", "rss_deficit"), cells, strict=False):
            m = s[metric]
            assert cell == f"{m['mean']:.2f} <span class=meta>[{m['ci_low']:.2f}, {m['ci_high']:.2f}]</span>"
        assert cells[4:6] == [f"{s['rss_deficit_sum']:.1f}", str(s["episodes_with_collision"])]
        assert cells[7] == str(s["sim_steps"])
    # the per-scene table shows each episode's collision / proximity violation
    for row_file in (campaign / "episodes").glob("*/*.json"):
        e = json.loads(row_file.read_text())
        assert f"{e['collision']:.1f} / {e['proximity']:.1f}" in text
    assert main(["report", str(campaign), "--out", str(out)]) == 2
    assert main(["report", str(campaign), "--out", str(out), "--force"]) == 0


def test_report_of_a_half_finished_campaign_says_what_is_missing(tmp_path, campaign: Path) -> None:
    folder = tmp_path / "half"
    shutil.copytree(campaign, folder)
    (folder / "episodes" / "sunny" / "scene_0004.json").unlink()
    (folder / "report.html").unlink(missing_ok=True)
    assert main(["report", str(folder)]) == 0
    assert "not finished: missing episodes {'sunny': 1}" in (folder / "report.html").read_text()
    empty = tmp_path / "empty"
    shutil.copytree(campaign, empty)
    shutil.rmtree(empty / "episodes")
    assert main(["report", str(empty), "--out", str(tmp_path / "x.html")]) == 2


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--policies", "sunny,bogus"], "unknown policy 'bogus'; allowed: sunny, random, constant, agent, cmaes"),
        (["--policies", "agent"], "policy 'agent' needs --agent"),
        (["--policies", "sunny", "--agent", "nowhere"], "--agent 'nowhere' does not exist"),
        (["--policies", "sunny", "--scenes", "0"], "--scenes = 0; allowed: an integer >= 1"),
        (["--policies", "cmaes", "--search-budget", "1"], "--search-budget = 1; allowed: an integer >= 2"),
        (["--policies", "sunny", "--seed", "-1"], "--seed = -1; allowed: an integer >= 0"),
    ],
)
def test_evaluate_bad_input_exits_2(tmp_path, catalog: str, capsys, argv: list[str], message: str) -> None:
    rc = main(["evaluate", "--catalog", catalog, "--out", str(tmp_path / "e"), "--quiet", *argv])
    assert rc == 2
    assert message in capsys.readouterr().err


def test_agent_and_search_policies(tmp_path, catalog: str) -> None:
    """A (freshly initialised) PPO agent plays from its run folder; CMA-ES spends its budget and keeps its
    best episode."""
    from stable_baselines3 import PPO

    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
    from genesis_rl.training.config import RunConfig

    run = tmp_path / "run"
    run.mkdir()
    cfg = RunConfig(env=EnvConfig(catalog=catalog, episode_steps=20, system="blind"))
    (run / "config.toml").write_text(cfg.to_toml())
    env = GenesisEnv(cfg.env)
    PPO("CnnPolicy", env, n_steps=16, batch_size=8, seed=0, device="cpu").save(run / "agent.zip")
    env.close()
    out = tmp_path / "eval"
    rc = main(["evaluate", "--agent", str(run), "--policies", "agent,cmaes", "--catalog", catalog, "--scenes", "1",
               "--steps", "20", "--search-budget", "4", "--out", str(out), "--quiet", "--no-report"])
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["policies"]["agent"]["sim_steps"] == 20
    assert summary["policies"]["cmaes"]["sim_steps"] == 4 * 20
    row = json.loads(next((out / "episodes" / "cmaes").glob("*.json")).read_text())
    assert row["return"] == pytest.approx(max(row["extra"]["search_returns"]), abs=1e-3)
    assert "agent_vs_cmaes" in summary["comparisons"]
    assert os.path.isfile(out / "campaign.json")
    # the same agent, its path spelled another way (its agent.zip): resuming is allowed, nothing is left to run
    rc = main(["evaluate", "--agent", str(run / "agent.zip"), "--policies", "agent,cmaes", "--catalog", catalog,
               "--scenes", "1", "--steps", "20", "--search-budget", "4", "--out", str(out), "--quiet",
               "--no-report", "--resume"])
    assert rc == 0


def test_rows_of_an_older_labeller_are_relabelled(tmp_path, campaign: Path, hit: dict) -> None:
    from genesis_rl.campaigns.summary import summarize_campaign

    folder = tmp_path / "old"
    shutil.copytree(campaign, folder)
    path = folder / "episodes" / "random" / f"{hit['name']}.json"
    row = json.loads(path.read_text())
    row.pop("labeller_version")
    row["failure_mode"] = "detected"
    path.write_text(json.dumps(row))
    summary = summarize_campaign(folder)
    assert json.loads(path.read_text())["failure_mode"] == "non_detection"
    assert summary["policies"]["random"]["failure_modes"]["non_detection"] == 1


def test_an_episode_whose_simulator_dies_is_retried_after_reconnecting(tmp_path, catalog: str) -> None:
    from genesis_rl.adversaries import POLICIES, SunnyPolicy, register_policy
    from genesis_rl.core.errors import SimulatorLost

    class Flaky(SunnyPolicy):
        """Loses the simulator on its first episode, as a CARLA server that dies mid-episode."""

        name = "flaky_test"
        calls = 0
        failures_left = 1

        def run_episode(self, runner, scene, episode_seed):  # noqa: ANN001, ANN201
            type(self).calls += 1
            if type(self).failures_left > 0:
                type(self).failures_left -= 1
                runner.run(self.act, scene, episode_seed)  # part of an episode, then the server is gone
                raise SimulatorLost("server at localhost:2000 stopped answering")
            return super().run_episode(runner, scene, episode_seed)

    register_policy(Flaky)
    try:
        folder = tmp_path / "flaky"
        with pytest.warns(UserWarning, match="simulator lost .* reconnecting, retry 1 of 2"):
            summary = run_campaign(_spec(catalog, policies=("flaky_test",), scenes=1, steps=20), folder,
                                   progress=False)
        assert summary["policies"]["flaky_test"]["episodes"] == 1 and Flaky.calls == 2
        import pyarrow.parquet as pq

        assert pq.read_table(next((folder / "steps" / "flaky_test").glob("*.parquet"))).num_rows == 20
        Flaky.failures_left = 5  # failing again: with no retries left the campaign stops, nothing half-written
        with pytest.raises(SimulatorLost):
            run_campaign(_spec(catalog, policies=("flaky_test",), scenes=1, steps=20, options={"retries": 0}),
                         tmp_path / "dead", progress=False)
        assert not list((tmp_path / "dead").glob("episodes/*/*.json"))
        assert not list((tmp_path / "dead").glob("steps/*/*.parquet"))
    finally:
        POLICIES.pop("flaky_test", None)


@pytest.mark.parametrize(("edit", "message"), [
    (lambda r: r["camera"].update(width="x"), "field 'camera.width' = 'x'; allowed: an integer in 16..4096"),
    (lambda r: r.update(knobs=["nope"]), "field 'knobs' = \"['nope']\"; allowed: a list of knob names"),
    (lambda r: r["schedule"].__setitem__(0, [0.0]), "field 'schedule[0]'"),
    (lambda r: r["schedule"][1].__setitem__(0, 500.0), "schedule[1] fog_density = 500.0; allowed 0..100"),
    (lambda r: r.update(episode_seed="x"), "field 'episode_seed' = 'x'; allowed: an integer >= 0"),
    (lambda r: r.update(system="blind"), "field 'system' = 'blind'; allowed: an object"),
    (lambda r: r.update(step_digest=5), "field 'step_digest' = '5'; allowed: a hex string or null"),
    (lambda r: r["violations"].update(collision="x"), "field 'violations.collision' = 'x'; allowed: a number"),
])
def test_a_hand_edited_record_is_refused_naming_the_field(tmp_path, hit: dict, capsys, edit, message) -> None:
    rec = json.loads((hit["record"]).read_text())
    edit(rec)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(rec))
    assert main(["replay", str(bad), "--out", str(tmp_path / "o"), "--quiet", "--no-gif"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_damaged_campaign_files_are_named_not_tracebacks(tmp_path, campaign: Path, hit: dict, capsys) -> None:
    copy = tmp_path / "camp"
    shutil.copytree(campaign, copy)
    episode = sorted((copy / "episodes").glob("*/*.json"))[0]
    episode.write_text('{"x": 1}')
    assert main(["report", str(copy), "--force"]) == 2
    assert f"'{episode}' is damaged: field 'violations' is missing or empty" in capsys.readouterr().err
    row = json.loads((campaign / episode.relative_to(copy)).read_text())
    episode.write_text(json.dumps({**row, "collision_events": "two"}))
    assert main(["report", str(copy), "--force"]) == 2
    assert f"'{episode}' is damaged: field 'collision_events' = 'two'; expected an integer" in capsys.readouterr().err
    # the actor events the cut-in table and the blame read as numbers are checked too
    event = {"kind": "cut_in", "vehicle_id": 2, "onset_s": 1.0, "perceivable_s": 1.3, "perceived_ttc_s": "soon"}
    episode.write_text(json.dumps({**row, "actor_events": [event]}))
    assert main(["report", str(copy), "--force"]) == 2
    assert (f"'{episode}' is damaged: field 'actor_events[0].perceived_ttc_s' = 'soon'; expected a number or null"
            in capsys.readouterr().err)
    episode.write_text(json.dumps({**row, "actor_events": {"kind": "cut_in"}}))
    assert main(["report", str(copy), "--force"]) == 2
    assert "field 'actor_events' = {'kind': 'cut_in'}; expected a list of events" in capsys.readouterr().err
    episode.write_text(json.dumps(row))
    assert main(["report", str(copy), "--force"]) == 0
    # a user error is reported as itself, not as damage (it was "holds a damaged or foreign file" before)
    assert main(["report", str(copy)]) == 2
    err = capsys.readouterr().err
    assert "exists; pass --force to rebuild it" in err and "is damaged" not in err and "foreign" not in err
    # a truncated step file is named where it is read
    hit_dir = sorted(p for p in (copy / "frames").glob("*/*") if p.is_dir())[0]
    steps = copy / "steps" / hit_dir.parent.name / f"{hit_dir.name}.parquet"
    steps.write_bytes(steps.read_bytes()[:200])
    assert main(["export", str(copy), "--format", "coco", "--out", str(tmp_path / "x")]) == 2
    assert f"'{steps}' is damaged: not a readable Parquet file" in capsys.readouterr().err
    episode.write_text("{")
    assert main(["report", str(copy), "--force"]) == 2
    assert f"episode file '{episode}' is not valid JSON" in capsys.readouterr().err
    assert main(["replay", str(hit["record"]), "--out", str(tmp_path / "r"),
                 "--gif-seconds", "-1"]) == 2
    assert "--gif-seconds = -1; allowed: an integer >= 0" in capsys.readouterr().err
    assert main(["replay", str(copy), "--out", str(tmp_path / "r")]) == 2
    assert f"record '{copy}' is a folder" in capsys.readouterr().err
    assert main(["replay", str(hit["record"]), "--weights", "w.pt",
                 "--out", str(tmp_path / "r")]) == 2
    assert "--weights applies to records of --system builtin, yolo or a plug-in" in capsys.readouterr().err


def test_report_and_export_refuse_a_steps_file_a_row_short(tmp_path, campaign: Path, capsys) -> None:
    """A file that parses but lost its last row (a copy cut short, say) is named, not plotted as a shorter run."""
    import pyarrow.parquet as pq

    copy = tmp_path / "camp"
    shutil.copytree(campaign, copy)
    hit_dir = sorted(p for p in (copy / "frames").glob("*/*") if p.is_dir())[0]
    steps = copy / "steps" / hit_dir.parent.name / f"{hit_dir.name}.parquet"
    table = pq.read_table(steps)
    pq.write_table(table.slice(0, table.num_rows - 1), steps)
    message = f"'{steps}' is damaged: it holds {table.num_rows - 1} step rows where its episode row says"
    assert main(["export", str(copy), "--format", "coco", "--out", str(tmp_path / "x")]) == 2
    assert message in capsys.readouterr().err
    assert main(["report", str(copy), "--force"]) == 2
    assert message in capsys.readouterr().err


def _claiming(steps: Path, rows: int, monkeypatch) -> None:
    """Replace an episode's steps file by a small one whose footer claims ``rows`` rows, and make reading its rows
    fail: a refusal must come from the footer, before any row is read."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.table({"step": pa.array(np.zeros(rows, np.int32))}), steps)
    assert steps.stat().st_size < 1_000_000 and pq.ParquetFile(steps).metadata.num_rows == rows
    real = pq.read_table

    def guarded(source, *args, **kwargs):
        assert pq.ParquetFile(source).metadata.num_rows != rows, f"the rows of {source} were read"
        return real(source, *args, **kwargs)

    monkeypatch.setattr(pq, "read_table", guarded)


@pytest.mark.parametrize("rows", [50_000, 2_000_000])  # under the ceiling of 100,001 rows, and far above it
@pytest.mark.parametrize("command", [["report", "{copy}", "--force"],
                                     ["export", "{copy}", "--format", "coco", "--out", "{out}"],
                                     ["export", "{copy}", "--format", "yolo", "--out", "{out}"]])
def test_a_steps_file_claiming_more_rows_than_its_episode_is_refused_from_its_footer(
        tmp_path, campaign: Path, capsys, monkeypatch, command, rows) -> None:
    copy = tmp_path / "camp"
    shutil.copytree(campaign, copy)
    hit_dir = sorted(p for p in (copy / "frames").glob("*/*") if p.is_dir())[0]  # an episode the export reads
    steps = copy / "steps" / hit_dir.parent.name / f"{hit_dir.name}.parquet"
    _claiming(steps, rows, monkeypatch)
    args = [a.format(copy=copy, out=tmp_path / "x") for a in command]
    assert main(args) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"'{steps}' is damaged: " in line
    assert (f"it holds {rows:,} step rows where its episode row says {STEPS} steps" if rows < 100_000 else
            f"it claims {rows:,} step rows; an episode has at most") in line
    assert not (tmp_path / "x").exists()


def test_a_resumed_campaign_sets_aside_a_steps_file_of_another_length_to_play_it_again(
        tmp_path, campaign: Path, monkeypatch) -> None:
    """evaluate --resume asks each kept episode whether it is done: one whose steps file holds another count of
    rows than its row states is not, and its files are set aside (the episode then runs again)."""
    import pyarrow.parquet as pq

    from genesis_rl.campaigns.campaign_folder import episode_done

    copy = tmp_path / "camp"
    shutil.copytree(campaign, copy)
    steps = sorted((copy / "steps" / "sunny").glob("*.parquet"))[0]
    scene = int(steps.stem.split("_")[1])
    assert episode_done(copy, "sunny", scene, resume=True)
    _claiming(steps, 50_000, monkeypatch)
    with pytest.warns(UserWarning, match=f"sunny {steps.stem} is damaged .*it holds 50,000 step rows"):
        assert not episode_done(copy, "sunny", scene, resume=True)
    assert not steps.exists() and not (copy / "episodes" / "sunny" / f"{steps.stem}.json").exists()
    (aside,) = (copy / "damaged").glob(f"*/sunny/{steps.name}")
    assert pq.ParquetFile(aside).metadata.num_rows == 50_000


def test_export_says_when_the_frames_of_collisions_were_deleted(tmp_path, campaign: Path, capsys) -> None:
    copy = tmp_path / "camp"
    shutil.copytree(campaign, copy)
    shutil.rmtree(copy / "frames")
    assert main(["export", str(copy), "--format", "yolo", "--out", str(tmp_path / "x")]) == 2
    assert "episode(s) with a collision but no kept frames" in capsys.readouterr().err


def test_resume_runs_damaged_episodes_again_and_refuses_a_changed_rulebook(tmp_path, campaign: Path, catalog: str,
                                                                           hit: dict) -> None:
    """Issue 21 item 4: a damaged episode found on resume is run again (not kept), and the campaign pins the
    rulebook's content, so resuming under another rulebook is refused, naming it."""
    folder = tmp_path / "resumed"
    shutil.copytree(campaign, folder)
    steps = folder / "steps" / "random" / f"{hit['name']}.parquet"
    steps.write_bytes(steps.read_bytes()[:300])  # a disk that filled up mid-write
    with pytest.warns(UserWarning, match=f"random {hit['name']} is damaged"):
        summary = run_campaign(_spec(catalog), folder, resume=True, progress=False)
    assert json.loads((folder / "run_time.json").read_text())["episodes_run"] == 1
    assert summary["policies"] == json.loads((campaign / "summary.json").read_text())["policies"]
    assert list((folder / "damaged").glob(f"*/random/{hit['name']}.parquet"))  # set aside, not deleted
    rulebook = tmp_path / "rulebook.toml"
    rulebook.write_text('[[rules]]\nname = "collision"\n[[rules]]\nname = "proximity"\nparams = { distance = 9.0 }\n')
    with pytest.raises(UserInputError, match="--resume: rulebook changed since the campaign"):
        run_campaign(_spec(catalog, env={"system": "blind", "rulebook": str(rulebook)}), folder, resume=True,
                     progress=False)
