"""The benchmark's yardstick: failures that count only when they reproduce in a fresh world, a member whose
weakness only a reacting adversary can time, and the rank statistics corrected for ties."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from genesis_rl.adversaries.base import PolicyContext
from genesis_rl.adversaries.scripted import FixedOnset, StallWatcher
from genesis_rl.benchmark.metrics import Trial
from genesis_rl.benchmark.ranks import betainc, compare_ranks, f_sf
from genesis_rl.benchmark.reproduce import rerun_seeds
from genesis_rl.sut.system.stall import stall_start
from genesis_rl.sut.zoo.members import zoo_member
from genesis_rl.sut.zoo.trigger import STALE_HOLD_S, stale_frames
from genesis_rl.world.step_record import (
    CollisionStep,
    EgoStep,
    LeadStep,
    PerceptionStep,
    RecordedDetection,
    StepRecord,
)

DT = 0.05
BOX = RecordedDetection((100.0, 80.0, 140.0, 110.0), 0.9, (30.0, 0.0, 0.0))


def _record(i: int, box: RecordedDetection | None, lead_decel: float = 0.0, speed: float = 20.0,
            hit: bool = False) -> StepRecord:
    dets = () if box is None else (box,)
    return StepRecord(step=i + 1, time_s=round((i + 1) * DT, 3), ego=EgoStep(speed, 0.0, 0.0, 0.0, "follow"),
                      lead=LeadStep(3, 30.0, 20.0, 30.0, True), perception=PerceptionStep(len(dets), 1, 0.5, dets, ()),
                      collision=CollisionStep(hit, speed if hit else 0.0, 3 if hit else -1),
                      knobs={"lead_decel": lead_decel}, odd_status="inside")


def _moving_box(i: int) -> RecordedDetection:
    return RecordedDetection((100.0 + i, 80.0, 140.0 + i, 110.0), 0.9, (30.0 - 0.1 * i, 0.0, 0.0))


# -- the primary score ------------------------------------------------------------------------------------
def test_a_failure_is_confirmed_only_when_reported_triggered_avoidable_and_reproduced():
    # a search's candidate failed, its reported episode neither reached nor failed: raw, never confirmed
    candidate_only = Trial(1, 1536, None, None, first_failure_steps=10, reruns=10, reproduced=10)
    assert candidate_only.failed and candidate_only.avoidable and not candidate_only.confirmed(control=False)
    good = Trial(2, 256, 40, 90, reruns=10, reproduced=5)
    assert good.triggered and good.reproducible and good.confirmed(control=False)
    assert not Trial(2, 256, 40, 90, reruns=10, reproduced=4).confirmed(control=False)  # under half
    assert not Trial(2, 256, 40, 90, unavoidable=True, reruns=10, reproduced=10).confirmed(control=False)
    assert not Trial(2, 256, 95, 90, reruns=10, reproduced=10).confirmed(control=False)  # failed before reaching
    assert not Trial(2, 256, 40, 90).confirmed(control=False)  # never re-run: not reproducible
    assert Trial(2, 256, 40, 90).confirmed(control=False, rerun=False)  # a benchmark without re-runs
    # on a control any in-ODD failure of the reported episode counts, reached or not
    assert Trial(3, 256, None, 90, reruns=2, reproduced=1).confirmed(control=True)


def test_rerun_world_seeds_are_fresh_per_member_trial_and_scene():
    seeds = rerun_seeds(0, "stall_braking", 0, 4, 10)
    assert len(set(seeds)) == 10 and seeds == rerun_seeds(0, "stall_braking", 0, 4, 10)
    others = [rerun_seeds(1, "stall_braking", 0, 4, 10), rerun_seeds(0, "latency_braking", 0, 4, 10),
              rerun_seeds(0, "stall_braking", 1, 4, 10), rerun_seeds(0, "stall_braking", 0, 5, 10)]
    assert all(not set(seeds) & set(o) for o in others)


# -- statistics ---------------------------------------------------------------------------------------------
TABLE = {"a": {"x": 0.5, "y": 0.0, "z": 0.0, "w": 0.1}, "b": {"x": 0.4, "y": 0.0, "z": 0.1, "w": 0.1},
         "c": {"x": 0.6, "y": 0.2, "z": 0.0, "w": 0.0}, "d": {"x": 0.3, "y": 0.0, "z": 0.0, "w": 0.2}}


def test_friedman_is_corrected_for_ties_and_iman_davenport_given():
    r = compare_ranks(TABLE, ["x", "y", "z", "w"])
    # by hand: rank sums 4, 13, 13, 10 over n = 4 members, k = 4 policies give 8.1 uncorrected; one tied pair
    # a row (t^3 - t = 6 each, 24 in all) divides it by 1 - 24 / (n k (k^2 - 1)) = 0.9 -> 9.0
    assert r["friedman_chi2"] == pytest.approx(9.0)
    assert r["friedman_p"] == pytest.approx(0.029291, abs=1e-6)
    # Iman-Davenport: F = (n - 1) chi2 / (n (k - 1) - chi2) = 3 * 9 / 3 = 9 on (3, 9) degrees of freedom
    assert r["iman_davenport_f"] == pytest.approx(9.0)
    assert r["iman_davenport_p"] == pytest.approx(0.004505, abs=1e-6)
    everyone_ties = compare_ranks({s: {"x": 0.0, "y": 0.0} for s in "abc"}, ["x", "y"])
    assert everyone_ties["friedman_chi2"] == 0.0 and everyone_ties["friedman_p"] == 1.0


def test_the_f_tail_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for x, d1, d2 in ((2.5, 3, 9), (0.3, 5, 40), (9.0, 3, 9), (40.0, 1, 2), (1.0, 6, 6)):
        assert f_sf(x, d1, d2) == pytest.approx(float(stats.f.sf(x, d1, d2)), rel=1e-9, abs=1e-12)
    assert betainc(2.0, 3.0, 0.0) == 0.0 and betainc(2.0, 3.0, 1.0) == 1.0
    table = [[TABLE[s][p] for s in TABLE] for p in "xyzw"]
    assert compare_ranks(TABLE, list("xyzw"))["friedman_chi2"] == pytest.approx(
        float(stats.friedmanchisquare(*table).statistic))


# -- the reactive member ------------------------------------------------------------------------------------
def test_the_stall_is_drawn_from_the_world_seed_inside_the_members_window():
    m = zoo_member("stall_braking")
    kw = m.system_kwargs
    starts = [stall_start(s, kw["earliest_s"], kw["latest_s"]) for s in range(400)]
    assert min(starts) >= kw["earliest_s"] and max(starts) < kw["latest_s"]
    assert np.std(starts) > 0.25 * (kw["latest_s"] - kw["earliest_s"])  # spread: no fixed time knows it
    episode_s = m.env["episode_steps"] * DT
    assert kw["latest_s"] + kw["warning_s"] + kw["stall_s"] < episode_s  # the stall always ends in the episode
    assert stall_start(7, 4.0, 28.0) == stall_start(7, 4.0, 28.0) != stall_start(8, 4.0, 28.0)


def test_stale_frames_flag_the_repeats_and_the_region_needs_braking_during_them():
    boxes = [_moving_box(i) for i in range(10)] + [_moving_box(10)] * 6 + [_moving_box(i) for i in range(16, 40)]
    recs = [_record(i, b, lead_decel=6.0 if i >= 30 else 0.0) for i, b in enumerate(boxes)]
    flags = stale_frames(recs)
    assert not any(flags[:11]) and all(flags[11:16])
    hold = int(round(STALE_HOLD_S / DT))
    assert all(flags[16:16 + hold - 1]) and not any(flags[16 + hold + 1:])  # set for STALE_HOLD_S after
    region = zoo_member("stall_braking").trigger
    assert region.needs_sequence and region.reached(recs) is None  # braking only long after the repeats
    braking = [_record(i, b, lead_decel=6.0 if i >= 12 else 0.0) for i, b in enumerate(boxes)]
    assert region.reached(braking) == 12
    empty = [_record(i, None, lead_decel=6.0) for i in range(10)]  # nothing detected never reads as a repeat
    assert not any(stale_frames(empty))


class _ScriptedRunner:
    """Plays ``act`` over given records, as a campaign's runner would, and keeps its actions."""

    def __init__(self, records: list[StepRecord], knobs: tuple[str, ...]) -> None:
        self.records, self.knobs, self.last_record, self.actions = records, knobs, None, []

    def run(self, act, scene, episode_seed, start=None, start_head=False):  # noqa: ANN001, ANN201
        for rec in [None, *self.records]:
            self.last_record = rec
            self.actions.append(act(None))
        return SimpleNamespace(records=self.records)


def test_the_watcher_brakes_the_lead_at_the_first_repeat_and_the_fixed_onset_at_its_time():
    knobs = ("fog_density", "lead_decel")
    boxes = [_moving_box(i) for i in range(20)] + [_moving_box(20)] * 3 + [_moving_box(i) for i in range(23, 40)]
    runner = _ScriptedRunner([_record(i, b) for i, b in enumerate(boxes)], knobs)
    StallWatcher(PolicyContext(2, 0)).run_episode(runner, 0, 0)
    lead = [a[1] for a in runner.actions]
    first = lead.index(1.0)
    assert first == 22 and all(v == 1.0 for v in lead[first:]) and all(a[0] == 0.0 for a in runner.actions)
    # a standing ego's repeated boxes say nothing
    slow = _ScriptedRunner([_record(i, _moving_box(0), speed=1.0) for i in range(10)], knobs)
    StallWatcher(PolicyContext(2, 0)).run_episode(slow, 0, 0)
    assert all(a[1] == 0.0 for a in slow.actions)
    fixed = _ScriptedRunner([_record(i, b) for i, b in enumerate(boxes)], knobs)
    FixedOnset(PolicyContext(2, 0, options={"onset_s": 1.0})).run_episode(fixed, 0, 0)
    assert [a[1] for a in fixed.actions].index(1.0) == int(round(1.0 / DT))
    # on a member without the lead's braking the scripted policies hold every knob
    plain = _ScriptedRunner([_record(i, _moving_box(0)) for i in range(10)], ("fog_density",))
    StallWatcher(PolicyContext(1, 0)).run_episode(plain, 0, 0)
    assert all(not a.any() for a in plain.actions)


# -- the world's randomness, apart from the adversary's ------------------------------------------------------
def test_the_world_seed_redraws_traffic_and_sensor_noise_and_defaults_to_the_episode_seed():
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

    env = GenesisEnv(EnvConfig(map="highway", scenes=2, episode_steps=40, system="builtin"))
    hold = np.zeros(env.action_space.shape, np.float32)

    def drive(**options):  # noqa: ANN003, ANN202
        _, info = env.reset(options={"scene": 1, "episode_seed": 11, **options})
        for _ in range(40):
            env.step(hold)
        return info, [(r.lead.true_distance, r.ego.speed, r.perception.detections) for r in env.records], \
            env._sim.poses().copy()  # noqa: SLF001 - the NPCs' poses, which no record holds

    try:
        info, plain, poses = drive()
        assert info["world_seed"] == 11
        same_info, same, same_poses = drive(world_seed=11)
        assert same == plain and np.array_equal(same_poses, poses)
        fresh_info, fresh, fresh_poses = drive(world_seed=12)
        assert fresh_info["episode_seed"] == 11 and fresh_info["world_seed"] == 12
        assert not np.array_equal(fresh_poses, poses)  # the traffic drew its behaviour afresh
        assert [d for *_, d in fresh] != [d for *_, d in plain]  # and the camera its noise
    finally:
        env.close()


def test_zoo_truth_refuses_a_member_without_a_watcher_and_a_bad_out(tmp_path, capsys):
    from genesis_rl.commands.cli import main

    assert main(["zoo", "truth", "low_sun", "--out", str(tmp_path / "t.json")]) == 2
    assert "has no scripted reactive policy; allowed: stall_braking" in capsys.readouterr().err
    assert main(["zoo", "truth", "stall_braking", "--out", str(tmp_path / "t.csv")]) == 2
    assert "give a .json file" in capsys.readouterr().err
    assert main(["zoo", "truth", "stall_braking", "--held-out", "0", "--out", str(tmp_path / "t.json")]) == 2
    assert "--held-out = 0; allowed: an integer >= 1" in capsys.readouterr().err
    assert main(["zoo", "truth", "stall_braking", "--onsets", "2,x", "--out", str(tmp_path / "t.json")]) == 2
    assert "--onsets '2,x': give a comma list of numbers" in capsys.readouterr().err
    assert main(["zoo", "truth", "stall_braking", "--onsets", "2,-1", "--out", str(tmp_path / "t.json")]) == 2
    assert "every onset must be a finite number of seconds >= 0" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


def test_the_truth_plot_shows_both_policies_against_the_thresholds(tmp_path):
    from genesis_rl.benchmark.reactive_truth import plot_truth

    cell = {"counted": 3, "triggered": 3, "episodes": 10, "share": 0.3, "triggered_share": 0.3, "ci95": [0.07, 0.65]}
    result = {"member": "stall_braking", "onsets_s": [0.0, 1.0, 2.0], "tuning_episodes": 6, "held_out_episodes": 10,
              "tuning_counted_by_onset": {"0": 0, "1": 2, "2": 1}, "best_fixed_onset_s": 1.0,
              "reactive_policy": "stall_watcher", "reactive": {**cell, "counted": 2, "triggered": 8, "share": 0.2,
                                                               "triggered_share": 0.8, "ci95": [0.03, 0.56]},
              "best_fixed": cell}
    plot_truth(result, tmp_path / "t.png")
    from PIL import Image

    with Image.open(tmp_path / "t.png") as im:
        assert im.size[0] > 800 and im.size[1] > 300


def test_the_truth_counts_a_failure_as_the_benchmark_confirms_it_triggered_and_avoidable():
    from genesis_rl.benchmark.reactive_truth import Episode, _share

    def ep(reached, failure, unavoidable=None):
        return Episode("stall_watcher", None, 0, 1, reached, failure, unavoidable)

    episodes = [ep(100, 236, True), ep(100, 266, False), ep(300, 250, False), ep(None, 200, False), ep(50, None),
                ep(None, None)]
    assert [e.triggered for e in episodes] == [True, True, False, False, False, False]
    assert [e.counts for e in episodes] == [False, True, False, False, False, False]
    cell = _share(episodes)
    assert (cell["counted"], cell["triggered"], cell["unavoidable"], cell["failed"], cell["reached"]) == (1, 2, 1, 4, 4)
    assert cell["share"] == round(1 / 6, 4) and cell["triggered_share"] == round(2 / 6, 4)
    assert cell["ci95"][0] < cell["share"] < cell["ci95"][1]


def test_the_truth_blames_as_campaigns_do_the_careful_driver_first_the_oracle_only_without_it(monkeypatch):
    from types import SimpleNamespace

    import genesis_rl.labels.blame as blame
    import genesis_rl.labels.careful_driver as careful
    from genesis_rl.benchmark.reactive_truth import unavoidable

    asked = []

    def oracle() -> bool:
        asked.append(True)
        return False  # the oracle avoids it: a perception failure, avoidable

    outcome = SimpleNamespace(records=[], actor_events=["lead braked"])
    monkeypatch.setattr(blame, "visibility_evidence", lambda records, hit_at, dt: {"stoppable": False})
    monkeypatch.setattr(careful, "event_for_collision", lambda events, records, hit_at: events[0] if events else None)
    for collides in (True, False):  # the tester braked the lead: the careful driver alone decides
        monkeypatch.setattr(careful, "careful_driver_evidence", lambda *a, c=collides: {"collides": c})
        assert unavoidable(outcome, 5, 0.05, oracle) is collides
    assert asked == []
    # no actor event: not visible and stoppable, but the oracle system avoids it, so perception, avoidable
    assert unavoidable(SimpleNamespace(records=[], actor_events=[]), 5, 0.05, oracle) is False
    assert asked == [True]
    assert unavoidable(SimpleNamespace(records=[], actor_events=[]), 5, 0.05, lambda: True) is True


def test_a_steps_file_must_hold_as_many_rows_as_its_episode_row_says(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from genesis_rl.campaigns.campaign_files import read_step_records, read_steps
    from genesis_rl.core.errors import UserInputError
    from genesis_rl.world.step_record import to_rows

    path = tmp_path / "scene_0001.parquet"
    rows = to_rows([_record(i, _moving_box(i)) for i in range(3)])
    pq.write_table(pa.Table.from_pylist(rows), path)
    assert len(read_step_records(path, 3)) == 3 and len(read_steps(path)) == 3  # no count given: not checked
    with pytest.raises(UserInputError, match="holds 3 step rows where its episode row says 2 steps"):
        read_step_records(path, 2)
    with pytest.raises(UserInputError, match="holds 3 step rows where its episode row says 70 steps"):
        read_steps(path, columns=["step"], steps=70)
