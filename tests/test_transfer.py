"""The benchmark's transfer protocol: disjoint tuning and held-out scenes, schedules replayed exactly, costs
with tuning and training counted, and the break-even count of held-out scenes."""

from __future__ import annotations

import numpy as np
import pytest

from genesis_rl.adversaries.replay import Schedule, build_policy, replayed_schedule
from genesis_rl.benchmark.matrix import BenchmarkSpec
from genesis_rl.benchmark.transfer import break_even_scenes, break_even_table, transfer_costs
from genesis_rl.campaigns.campaign_spec import CampaignSpec, pick_scenes
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.knobs import Weather


def test_pick_scenes_without_exclude_draws_as_every_version_before():
    # the draw campaigns of before recorded: a change here would resume other scenes under their names
    rng = np.random.default_rng(7)
    before = sorted(int(i) for i in rng.choice(1199, size=5, replace=False))
    assert [s for s, _ in pick_scenes(1199, 5, 7)] == before
    assert pick_scenes(1199, 5, 7, ()) == pick_scenes(1199, 5, 7)


def test_excluded_scenes_are_never_drawn_and_the_draw_is_seeded():
    held = [s for s, _ in pick_scenes(30, 10, 3)]
    tuning = pick_scenes(30, 20, 3, tuple(held))
    assert not set(held) & {s for s, _ in tuning} and len(tuning) == 20
    assert tuning == pick_scenes(30, 20, 3, tuple(held))
    with pytest.raises(UserInputError, match=r"1\.\.20 .*less 10 excluded"):
        pick_scenes(30, 21, 3, tuple(held))


def test_a_campaign_spec_writes_exclude_only_when_given_and_reads_it_back():
    plain = CampaignSpec(policies=("sunny",), scenes=2)
    assert "exclude" not in plain.to_json()  # campaign.json files of before compare unchanged
    spec = CampaignSpec(policies=("sunny",), scenes=2, exclude=(4, 9))
    assert spec.to_json()["exclude"] == [4, 9] and CampaignSpec.from_json(spec.to_json()) == spec
    for bad in ((1, 1), (-1,), ("3",)):
        with pytest.raises(UserInputError, match="spec.exclude"):
            CampaignSpec(policies=("sunny",), exclude=bad)  # type: ignore[arg-type]


def _schedule(n: int) -> Schedule:
    base = Weather.default().values
    return Schedule(Weather.from_partial({"fog_density": 10.0}),
                    tuple(Weather({**base, "fog_density": float(i), "lead_decel": 0.5 * i}) for i in range(n)))


def test_a_schedule_round_trips_through_json_exactly_and_bad_ones_are_named():
    s = _schedule(5)
    assert Schedule.from_json(s.to_json(), "x") == s
    data = s.to_json()
    data["steps"]["fog_density"] = data["steps"]["fog_density"][:3]
    with pytest.raises(UserInputError, match=r"x\.steps: one non-empty list per knob, all of one length"):
        Schedule.from_json(data, "x")
    bad = s.to_json()
    bad["steps"]["fog_density"][2] = float("inf")
    with pytest.raises(UserInputError, match=r"x\.steps\.fog_density: finite numbers only"):
        Schedule.from_json(bad, "x")
    with pytest.raises(UserInputError, match="schedules.cem"):
        replayed_schedule({"schedules": {"cem": {"start": None}}}, "cem")
    assert replayed_schedule({"schedules": {"cem": s.to_json()}}, "cmaes") is None


def test_a_campaign_refuses_a_schedule_for_a_policy_it_does_not_play():
    from genesis_rl.campaigns.campaign_spec import check_spec

    spec = CampaignSpec(policies=("sunny", "cem"), scenes=1, options={"schedules": {"cmaes": _schedule(2).to_json()}})
    with pytest.raises(UserInputError, match=r"schedules names \['cmaes'\].*allowed: sunny, cem"):
        check_spec(spec)


def test_a_policy_named_in_schedules_replays_and_the_others_play_themselves():
    from genesis_rl.adversaries import CrossEntropySearch, PolicyContext
    from genesis_rl.adversaries.replay import ScheduleReplay

    ctx = PolicyContext(action_dim=5, seed=0, options={"schedules": {"cem": _schedule(3).to_json()}})
    assert isinstance(build_policy(CrossEntropySearch, "cem", ctx), ScheduleReplay)
    assert type(build_policy(CrossEntropySearch, "other", ctx)) is CrossEntropySearch


def test_break_even_is_where_the_agents_steps_per_confirmed_failure_meet_the_searchs():
    # T_a = 20,480 training steps at 0.5 a scene against a search tuned with 5,120 steps at 0.25 a scene, 160-step
    # episodes: (20480 * 0.25 - 5120 * 0.5) / (160 * 0.25) = 64 scenes
    n = break_even_scenes(20480, 0.5, 5120, 0.25, 160)
    assert n == pytest.approx(64.0)
    a, s = (20480 + n * 160) / (n * 0.5), (5120 + n * 160) / (n * 0.25)
    assert a == pytest.approx(s)  # at 64 scenes both cost 1,280 steps a confirmed failure
    assert break_even_scenes(20480, 0.2, 5120, 0.25, 160) is None  # fewer failures a scene: never pays
    assert break_even_scenes(0, 0.0, 5120, 0.25, 160) is None  # confirms nothing
    assert break_even_scenes(20480, 0.1, 5120, 0.0, 160) == 0.0  # the search confirms nothing
    assert break_even_scenes(100, 0.5, 5120, 0.25, 160) == 0.0  # cheaper from the first scene


def test_costs_count_training_once_and_tuning_every_trial():
    costs = transfer_costs([{"cem": 1280}, {"cem": 1280}], [{"cem": 320, "agent:r": 320}, {"cem": 320, "agent:r": 320}],
                           {"agent:r": 20480})
    assert costs["cem"] == {"tuning_steps": 2560, "training_steps": 0, "held_out_steps": 640, "total_steps": 3200}
    assert costs["agent:r"]["total_steps"] == 20480 + 640
    unknown = transfer_costs([{}], [{"agent:x": 160}], {"agent:x": None})
    assert unknown["agent:x"]["total_steps"] is None
    cells = {"cem": {"confirmed_rate": 0.25}, "agent:r": {"confirmed_rate": 0.5}, "sunny": {"confirmed_rate": 0.0}}
    # one trial's tuning (1,280) against the training: (20480 * 0.25 - 1280 * 0.5) / (160 * 0.25) = 112
    assert break_even_table(cells, costs, trials=2, episode_steps=160) == {"agent:r": {"cem": 112.0}}


def test_the_transfer_protocol_needs_a_search_and_is_written_only_when_chosen():
    with pytest.raises(UserInputError, match="protocol transfer: none of the policies"):
        BenchmarkSpec(members=("latency_braking",), policies=("sunny", "constant"), protocol="transfer")
    with pytest.raises(UserInputError, match="protocol = 'held'; allowed: per_scene, transfer"):
        BenchmarkSpec(members=("latency_braking",), policies=("cem",), protocol="held")
    with pytest.raises(UserInputError, match="tuning_scenes = 0"):
        BenchmarkSpec(members=("latency_braking",), policies=("cem",), protocol="transfer", tuning_scenes=0)
    plain = BenchmarkSpec(members=("latency_braking",), policies=("cem",)).to_json()
    assert "protocol" not in plain and "tuning_scenes" not in plain
    chosen = BenchmarkSpec(members=("latency_braking",), policies=("cem",), protocol="transfer", tuning_scenes=3)
    assert chosen.to_json()["protocol"] == "transfer" and chosen.to_json()["tuning_scenes"] == 3


def test_a_schedule_played_on_its_own_scene_is_the_episode_again_and_on_another_the_same_knobs(tmp_path):
    from genesis_rl.campaigns.episodes import CampaignRunner
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.sut.zoo.members import ZOO, env_settings

    member = ZOO["latency_braking"]
    generate_catalog(member.map, 4, 0, traffic=member.traffic).save(tmp_path / "catalog.json")
    spec = CampaignSpec(policies=("random",), map=member.map, scenes=2, steps=60, env=env_settings(member),
                        traffic=member.traffic)
    runner = CampaignRunner(spec, tmp_path)
    try:
        rng = np.random.default_rng(0)
        dim = runner.env.mapper.action_dim
        played = runner.run(lambda obs: rng.uniform(-1.0, 1.0, dim).astype(np.float32), 1, 5)
        assert max(r.knobs["lead_decel"] for r in played.records) > 0  # the lead brakes in it
        schedule = Schedule.of_episode(played.start, [r.knobs for r in played.records])
        again = runner.play_schedule(1, 5, schedule.start, schedule.steps)
        assert repr(again.records) == repr(played.records)  # the same episode, to the bit
        other = runner.play_schedule(2, 5, schedule.start, schedule.steps)
        assert [r.knobs for r in other.records] == [r.knobs for r in played.records]
        assert [r.ego for r in other.records] != [r.ego for r in played.records]  # another scene, another drive
        short = runner.play_schedule(1, 5, schedule.start, schedule.steps[:10])  # holds its last weather
        assert len(short.records) == 60 and all(r.knobs == played.records[9].knobs for r in short.records[9:])
    finally:
        runner.close()


def test_a_transfer_benchmark_tunes_on_other_scenes_and_replays_the_best_schedule_on_the_held_out_one(tmp_path):
    import json

    from genesis_rl.campaigns.campaign_files import read_step_records
    from genesis_rl.campaigns.loaded import load_typed_campaign
    from genesis_rl.commands.cli import main

    out = tmp_path / "bench"
    args = ["benchmark", "--quiet", "--out", str(out), "--members", "latency_braking", "--policies",
            "sunny,constant,cem", "--trials", "1", "--scenes", "1", "--protocol", "transfer", "--tuning-scenes", "1",
            "--search-budget", "2", "--steps", "160", "--reruns", "1"]
    assert main(args) == 0
    tuning = load_typed_campaign(out / "campaigns" / "latency_braking" / "trial_00_tuning")
    held = load_typed_campaign(out / "campaigns" / "latency_braking" / "trial_00")
    assert tuning.spec.policies == ("cem",) and tuning.spec.exclude == (1019,)
    (held_scene,) = {r.scene for rows in held.episodes.values() for r in rows}
    (tuned_scene,) = {r.scene for r in tuning.episodes["cem"]}
    assert held_scene == 1019 != tuned_scene  # the per-scene protocol's trial scene, never tuned on
    # the held-out episode of cem is its tuning episode's schedule, knob for knob, on another scene
    row = tuning.episodes["cem"][0]
    tuned_knobs = [r.knobs for r in read_step_records(tuning.folder.steps("cem", row.scene), row.steps)]
    played = held.episodes["cem"][0]
    assert [r.knobs for r in read_step_records(held.folder.steps("cem", held_scene), played.steps)] == tuned_knobs
    assert played["sim_steps"] == 160 and row["sim_steps"] == 2 * 160  # one episode held out, its budget tuning
    board = json.loads((out / "leaderboard.json").read_text())
    costs = board["transfer"]["members"]["latency_braking"]["costs"]
    assert costs["cem"] == {"tuning_steps": 320, "training_steps": 0, "held_out_steps": 160, "total_steps": 480}
    assert costs["constant"]["total_steps"] == 160
    assert board["transfer"]["members"]["latency_braking"]["tuned"]["cem"][0]["scene"] == tuned_scene
    # constant needs no tuning: on the held-out scene it fails as in the smoke benchmark's first trial
    assert board["cells"]["latency_braking"]["constant"]["confirmed"] == 1
    assert board["cells"]["latency_braking"]["constant"]["median_steps_to_failure"] == 101.0
    assert "Transfer protocol: each search tuned on its own scenes" in (out / "leaderboard.html").read_text()
    assert main([*args, "--resume"]) == 0  # the kept campaigns are the ones asked for, schedules included
    assert json.loads((out / "leaderboard.json").read_text())["transfer"] == board["transfer"]


def test_held_out_scenes_an_agent_trained_on_are_counted(monkeypatch):
    import genesis_rl.campaigns.campaign_spec as campaign_spec
    from genesis_rl.benchmark.transfer import seen_in_training

    held = CampaignSpec(policies=("agent",), map="urban", scenes=3)
    runs = {"all": {"map": "urban", "scenes": 1202}, "first_100": {"map": "urban", "scenes": 100},
            "other_seed": {"map": "urban", "catalog_seed": 1}, "file": {"catalog": "mine.json"},
            "highway": {"map": "highway"}}
    monkeypatch.setattr(campaign_spec, "env_settings_for", lambda run, config, system: runs[run])
    scenes = (12, 430, 1100)
    assert seen_in_training("all", held, scenes) == 3  # the default training catalog holds them all
    assert seen_in_training("first_100", held, scenes) == 1
    assert seen_in_training("other_seed", held, scenes) == seen_in_training("highway", held, scenes) == 0
    assert seen_in_training("file", held, scenes) is None
    free = CampaignSpec(policies=("agent",), map="urban", scenes=3, traffic="free_flow")
    assert seen_in_training("all", free, scenes) == 0  # a training env generates mixed traffic: other scenes


def test_a_schedules_option_that_is_not_an_object_is_refused_before_any_policy_is_built():
    from genesis_rl.campaigns.campaign_spec import check_spec

    spec = CampaignSpec(policies=("agent",), scenes=1, agent="runs/none", options={"schedules": [{"x": 1}]})
    with pytest.raises(UserInputError, match="campaign option schedules: an object of policy -> schedule"):
        check_spec(spec)
