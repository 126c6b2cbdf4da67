"""Blame: could a competent driver have avoided a collision, and was it perception or control that failed?

Measured, not guessed, from three pieces of evidence:

1. *visible and stoppable* (:func:`visibility_evidence`): going back from the impact, the first step at which
   the hit vehicle was within the visibility distance (its distance: the nearest visible point of its
   ground-truth box, or the true gap when it is the lead); from there, did the ego have room to stop at the
   speed it drove (``rules.rulebook.stopping_distance_m``: the UK Highway Code's thinking and braking
   distances, doubled braking on a wet road), and was it visible for at least the reaction time? The hit
   vehicle is treated as standing still, which a driver would need the most room for.
2. *speed for visibility*: did the ego drive faster than it could stop within the visibility in the window
   before the impact (the rule of the same name)?
3. a *counterfactual replay* with ground-truth perception (the ``oracle`` system: the same controller fed
   true boxes) on the same scene, seeds and weather trajectory: does the collision persist?

The label (:func:`blame_label`): ``perception`` when the oracle replay avoids the collision; else
``control`` when the vehicle was visible and stoppable, or when the ego drove too fast for the visibility
(a driver would have slowed down); else ``unavoidable``. When the tester's actor knob acted on the vehicle
hit (a cut-in, the lead braking), the careful-driver reference of UN R157 decides avoidable or not instead
of the visibility evidence (``evaluation.careful_driver``), and the failure names it as its ``reference``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from genesis_rl.loop.rules.rulebook import speed_for_visibility, stopping_distance_m
from genesis_rl.world.step_record import StepRecord

BLAMES = ("perception", "control", "unavoidable")
#: how far back before the impact the evidence is read [s]
WINDOW_S = 10.0
#: a driver's reaction time [s] (UK Highway Code: 0.67 s thinking time)
REACTION_S = 0.67
#: driving faster than the speed for visibility by more than this [m/s] (about 2 km/h) counts as too fast
TOO_FAST_TOLERANCE = 0.5


def vehicle_distance(record: StepRecord, vehicle_id: int) -> float | None:
    """The distance [m] to ``vehicle_id`` at a step: its box's nearest visible point when it is in the image,
    else the true gap when it is the lead; None when neither is known."""
    box = next((b for b in record.perception.gt_boxes if b.vehicle_id == vehicle_id), None)
    if box is not None:
        return float(box.distance_m)
    if record.lead.vehicle_id == vehicle_id and math.isfinite(record.lead.true_distance):
        return float(record.lead.true_distance)
    return None


def visibility_evidence(records: Sequence[StepRecord], hit_at: int, dt: float = 0.05,
                        reaction_s: float = REACTION_S) -> dict[str, Any]:
    """Was the vehicle hit at ``records[hit_at]`` visible, with room to stop, for long enough (see the module
    docstring)? Also: the largest excess over the speed for visibility in the window [m/s]."""
    vid = records[hit_at].collision.other_id
    start = max(0, hit_at - int(round(WINDOW_S / dt)))
    first: tuple[int, float] | None = None
    too_fast = 0.0
    for i in range(start, hit_at + 1):
        r = records[i]
        c = r.conditions
        visibility = c.visibility_m if c is not None else math.inf
        if c is not None:
            too_fast = max(too_fast, r.ego.speed - speed_for_visibility(c.visibility_m, c.road_state, reaction_s))
        d = vehicle_distance(r, vid)
        if first is None and d is not None and d <= visibility:
            first = (i, d)
    out: dict[str, Any] = {"too_fast_for_visibility_m_s": round(too_fast, 3)}
    if first is None:
        return {**out, "visible": False, "stoppable": False, "visible_s": 0.0}
    i, d0 = first
    r = records[i]
    road = r.conditions.road_state if r.conditions is not None else "dry"
    needed = stopping_distance_m(float(r.ego.speed), road, reaction_s)
    visible_s = (hit_at - i) * dt
    return {**out, "visible": True, "visible_s": round(visible_s, 3), "distance_when_visible_m": round(d0, 2),
            "speed_when_visible_m_s": round(float(r.ego.speed), 2), "stopping_distance_m": round(needed, 2),
            "stoppable": bool(d0 >= needed and visible_s >= reaction_s)}


def blame_label(evidence: dict[str, Any], oracle_collides: bool | None,
                careful_driver: dict[str, Any] | None = None) -> str:
    """perception / control / unavoidable from the evidence (module docstring). Without a counterfactual
    (``oracle_collides`` None), a visible, stoppable collision is charged to control. When an actor knob
    acted on the vehicle hit, the careful-driver reference (``evaluation.careful_driver``) decides whether it
    was avoidable: unavoidable when that driver collides too; else perception or control as above, never
    unavoidable (a careful driver avoided it)."""
    if careful_driver is not None:
        if careful_driver["collides"]:
            return "unavoidable"
        return "perception" if oracle_collides is False else "control"
    if oracle_collides is False:
        return "perception"
    if evidence.get("stoppable") or evidence.get("too_fast_for_visibility_m_s", 0.0) > TOO_FAST_TOLERANCE:
        return "control"
    return "unavoidable"


#: what decides avoidable or not when no actor knob acted on the vehicle hit
VISIBILITY_REFERENCE = "visible and stoppable (UK Highway Code stopping distances)"


def reference_name(careful_driver: dict[str, Any] | None) -> str:
    """The reference that decided whether a collision was avoidable, as the report names it."""
    return VISIBILITY_REFERENCE if careful_driver is None else str(careful_driver["reference"])
