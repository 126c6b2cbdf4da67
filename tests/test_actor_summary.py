"""The cut-in table of a campaign's summary (issue 32): counted from crafted episode rows by hand."""

from __future__ import annotations

import pytest

from genesis_rl.labels.actor_summary import cut_in_html, cut_in_markdown, cut_in_summary


def _cut(ttc: float, perceived: float | None, closing: float) -> dict:
    e = {"kind": "cut_in", "vehicle_id": 2, "onset_s": 1.0, "perceivable_s": 1.3, "ttc_s": ttc, "gap_m": ttc * closing,
         "closing_m_s": closing}
    if perceived is not None:
        e["perceived_ttc_s"] = perceived
    return e


def test_cut_ins_are_counted_at_r157s_perceivable_moment_and_older_rows_at_their_onset():
    braking = {"kind": "lead_braking", "vehicle_id": 3, "onset_s": 2.0, "perceivable_s": 2.0}
    rows = [{"actor_events": [_cut(1.9, 1.6, 9.8), braking]},
            {"actor_events": [_cut(5.0, 4.7, 2.0), _cut(2.2, 1.7, 3.0)]}, {"actor_events": []}, {}]
    s = cut_in_summary(rows)
    # 1.6 s at 35 km/h is inside R157's boundary (1.06 s there); 1.7 s at 10.8 km/h too
    assert s == {"cut_ins": 3, "episodes": 2, "never_perceivable": 0, "under_4s": 2, "at_r157_boundary": 1,
                 "beyond_r157": 0, "shortest_ttc_s": 1.6, "median_ttc_s": 1.7, "largest_closing_m_s": 9.8,
                 "measured_at": "perceivable"}
    # 0.25 on: a cut-in never perceivable has no time-to-collision; one perceivable while not closing, inf
    never = {**_cut(3.0, None, 2.0), "perceivable_s": None}
    not_closing = _cut(3.0, None, 2.0)
    s = cut_in_summary([*rows, {"actor_events": [never, not_closing]}])
    assert s is not None and s["cut_ins"] == 5 and s["never_perceivable"] == 1 and s["under_4s"] == 2
    beyond = cut_in_summary([{"actor_events": [_cut(1.3, 0.9, 10.0)]}])  # 0.9 s at 36 km/h: R157 asks 1.08 s
    assert beyond is not None and beyond["beyond_r157"] == 1 and beyond["at_r157_boundary"] == 1
    # a campaign before 0.25 has no perceived_ttc_s: its onset's time-to-collision counts, and the table says so
    old = cut_in_summary([{"actor_events": [_cut(1.6, None, 5.0), {**_cut(8.0, None, 1.0), "perceivable_s": None}]}])
    assert old is not None and old["at_r157_boundary"] == 1 and old["measured_at"] == "onset"
    assert old["never_perceivable"] is None and old["under_4s"] == 1
    assert cut_in_summary([{"actor_events": [braking]}]) is None and cut_in_summary([]) is None


def test_the_cut_in_table_appears_only_where_a_policy_made_one():
    one = cut_in_summary([{"actor_events": [_cut(1.9, 1.6, 9.8)]}])
    policies = {"random": {"episodes": 2}, "constant": {"cut_ins": one}}
    md = cut_in_markdown(policies)
    assert len(md) == 4 and md[-1] == "| constant | 1 (1) | 0 | 1 | 1 | 0 | 1.60 / 1.60 s | 9.8 m/s | perceivable |"
    page = "".join(cut_in_html(policies))
    assert "<td class=l>constant</td>" in page and "random" not in page
    assert cut_in_markdown({"random": {}}) == [] and cut_in_html({"random": {}}) == []


def test_each_cut_in_is_a_point_against_r157s_boundary_and_a_hit_carries_its_blame():
    from genesis_rl.labels.actor_summary import R157_BOUNDARY, cut_in_points, fig_cut_ins, r157_boundary_ttc

    hit = {"scene": 628, "actor_events": [_cut(9.9, 9.6, 7.8), {**_cut(1.9, 1.6, 10.0), "vehicle_id": 7}],
           "failure": {"vehicle_id": 7, "hit": "cut in by the tester", "blame": "control"}}
    pts = cut_in_points([hit, {"scene": 3, "actor_events": [{**_cut(5.0, None, 2.0), "perceivable_s": None}]}])
    assert [(round(p["closing_km_h"], 2), p["ttc_s"], p["blame"]) for p in pts] == [
        (28.08, 9.6, None), (36.0, 1.6, "control")]  # the cut-in never perceivable has no point
    assert r157_boundary_ttc(35.0) == pytest.approx(1.06) and r157_boundary_ttc(5.0) == 0.48
    assert R157_BOUNDARY[-1] == (60.0, 1.64) and R157_BOUNDARY[0] == (10.0, 0.48)
    assert fig_cut_ins({"random": [{"actor_events": []}]}, {}) is None
    fig = fig_cut_ins({"constant": [hit]}, {"constant": "#756bb1"})
    assert fig is not None and len(fig.axes[0].collections) >= 3  # the boundary's band, the points, the hit


def test_every_cut_in_event_says_where_its_time_to_collision_was_taken():
    import math

    from genesis_rl.sim.interface import ActorEvent

    unseen = ActorEvent("cut_in", 2, 1.0, None, 3.0, 6.0, 2.0)
    assert unseen.as_dict()["perceived_ttc_s"] is None  # the key is there: measured the 0.25 way, not known
    seen = ActorEvent("cut_in", 2, 1.0, 1.3, 3.0, 6.0, 2.0, 2.7)
    assert seen.as_dict()["perceived_ttc_s"] == 2.7 and ActorEvent.from_dict(seen.as_dict()) == seen
    assert math.isnan(ActorEvent.from_dict(unseen.as_dict()).perceived_ttc_s)
    assert "perceived_ttc_s" not in ActorEvent("lead_braking", 3, 2.0, 2.0).as_dict()
    # a policy whose only cut-in was never perceivable is still counted the 0.25 way
    s = cut_in_summary([{"actor_events": [unseen.as_dict()]}])
    assert s is not None and s["measured_at"] == "perceivable" and s["never_perceivable"] == 1
