"""Why did the ego crash? Label each collision from the detection timeline of the vehicle that was hit.

The paper (Fig. 3) names three perception failure modes behind the agent's collisions. We read them off
the hit vehicle's timeline in a window before the impact, over the steps where it was *in view* (the
IoU's criteria: within range, visible enough, tall enough) and whether a detection matched it (IoU >= 0.3):

* ``non_detection``: matched in under ``min_detected_fraction`` of its in-view steps: the system never
  saw it.
* ``intermittent_detection``: the match flickers on and off at least ``min_flips`` times: the tracker
  keeps losing it, so the controller's gap estimate jumps.
* ``delayed_detection``: it was in view but unmatched for at least ``min_blind_s`` seconds, and the final
  unbroken detection run began under ``late_s`` seconds before the impact: seen, but too late to stop.
* ``lost_detection``: it was detected earlier but then missed, while in view, for at least
  ``min_blind_s`` seconds right before the impact: the system lost it.
* ``detected``: it was seen in time; the failure lies in control (or the scene), not perception.
* ``out_of_view``: it was never in view in the window (a side or rear impact the camera cannot see).

The thresholds live in ``FailureModeThresholds`` and docs/evaluation.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from genesis_rl.sim.geometry import in_view_values, iou_matrix
from genesis_rl.world.step_record import RecordedBox, StepRecord

FAILURE_MODES = ("non_detection", "intermittent_detection", "delayed_detection", "lost_detection", "detected",
                 "out_of_view")
MATCH_IOU = 0.3
#: bumped when the rules or thresholds change: summaries relabel older episode rows (3: their careful-driver verdicts
#: are made again where an older reference made them, ``campaigns.summary.rejudge_careful_driver``)
LABELLER_VERSION = 3


@dataclass(frozen=True)
class FailureModeThresholds:
    window_s: float = 4.0  # how far back before the impact the timeline is read [s]
    min_detected_fraction: float = 0.1  # below: non-detection
    min_flips: int = 4  # on/off changes at or above: intermittent detection
    min_blind_s: float = 1.0  # in view but unseen at least this long before the final detection run [s]
    late_s: float = 2.0  # the final detection run began less than this before the impact [s]

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def box_in_view(box: RecordedBox) -> bool:
    """``matching.in_view`` on a recorded box."""
    _, y0, _, y1 = box.box_xyxy
    return in_view_values(box.distance_m, box.visible_fraction, y1 - y0)


def detection_timeline(records: Sequence[StepRecord], vehicle_id: int) -> list[bool | None]:
    """Per record: None when ``vehicle_id`` is not in view, else whether a detection matched it."""
    out: list[bool | None] = []
    for r in records:
        box = next((b for b in r.perception.gt_boxes if b.vehicle_id == vehicle_id), None)
        if box is None or not box_in_view(box):
            out.append(None)
            continue
        dets = np.array([d.box_xyxy for d in r.perception.detections], np.float64).reshape(-1, 4)
        out.append(bool(len(dets) and iou_matrix(np.array([box.box_xyxy], np.float64), dets).max() >= MATCH_IOU))
    return out


def classify_timeline(timeline: Sequence[bool | None], dt: float,
                      thresholds: FailureModeThresholds | None = None) -> dict[str, Any]:
    """The failure mode of a timeline that ends at the impact (see the module docstring), with the figures
    that decided it."""
    th = thresholds or FailureModeThresholds()
    seen = [t for t in timeline if t is not None]
    info: dict[str, Any] = {"in_view_steps": len(seen), "detected_steps": int(sum(seen))}
    if not seen:
        return {"mode": "out_of_view", **info}
    fraction = sum(seen) / len(seen)
    flips = sum(1 for a, b in zip(seen, seen[1:], strict=False) if a != b)
    info.update(detected_fraction=round(fraction, 3), flips=flips)
    if fraction < th.min_detected_fraction:
        return {"mode": "non_detection", **info}
    if flips >= th.min_flips:
        return {"mode": "intermittent_detection", **info}
    # the last unbroken run of detections (over all steps: an out-of-view step breaks it)
    last_on = max(i for i, t in enumerate(timeline) if t)
    missed_after = sum(1 for t in timeline[last_on + 1:] if t is False)
    if missed_after * dt >= th.min_blind_s:
        return {"mode": "lost_detection", **info, "missed_before_impact_s": round(missed_after * dt, 3)}
    onset = last_on
    while onset > 0 and timeline[onset - 1]:
        onset -= 1
    blind_before = sum(1 for t in timeline[:onset] if t is False)
    onset_to_impact_s = (len(timeline) - onset) * dt
    info.update(onset_to_impact_s=round(onset_to_impact_s, 3), blind_before_s=round(blind_before * dt, 3))
    if blind_before * dt >= th.min_blind_s and onset_to_impact_s < th.late_s:
        return {"mode": "delayed_detection", **info}
    return {"mode": "detected", **info}


def label_collision(records: Sequence[StepRecord], thresholds: FailureModeThresholds | None = None,
                    dt: float = 0.05) -> dict[str, Any] | None:
    """The failure mode of the episode's first ego collision, or None when it has none."""
    th = thresholds or FailureModeThresholds()
    hit_at = next((i for i, r in enumerate(records) if r.collision.collided), None)
    if hit_at is None:
        return None
    vehicle = records[hit_at].collision.other_id
    start = max(0, hit_at - int(round(th.window_s / dt)))
    # the window ends at the step before the impact: the frame of the impact step comes after the tick
    result = classify_timeline(detection_timeline(records[start:hit_at], vehicle), dt, th)
    return {"step": records[hit_at].step, "vehicle_id": vehicle,
            "speed": float(records[hit_at].collision.speed), **result}
