"""The step record: what one closed-loop step produced, typed, with units.

It is the unit every later stage shares (docs/architecture.md): ``drive.ClosedLoop`` builds it after each
tick, the env adds the rulebook's terms and the reward's terms, and rules, the failure-mode labeller,
campaigns, summaries, reports, exports and replays read its fields by name. Serialisation to the flat
telemetry columns (Parquet, ``info``-friendly dicts) is one pair of functions, :meth:`StepRecord.to_row` and
:meth:`StepRecord.from_row`, so the column layout written by genesis-rl 0.4.0 is kept and old telemetry
loads. Boxes are kept as recorded (rounded as in the files), so a record read back from Parquet equals the
one that was written.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from genesis_rl.world.odd.conditions import Conditions


@dataclass(frozen=True, slots=True)
class RecordedBox:
    """A vehicle's ground-truth box as recorded: pixel box [x0, x1) x [y0, y1), the depth of its nearest
    visible point [m] and the share of it not hidden by others."""

    vehicle_id: int
    box_xyxy: tuple[int, int, int, int]
    distance_m: float
    visible_fraction: float
    truncated: bool

    def to_row(self) -> dict[str, Any]:
        return {"vehicle_id": self.vehicle_id, "box_xyxy": list(self.box_xyxy), "distance_m": self.distance_m,
                "visible_fraction": self.visible_fraction, "truncated": self.truncated}

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> RecordedBox:
        x0, y0, x1, y1 = row["box_xyxy"]
        return cls(int(row["vehicle_id"]), (x0, y0, x1, y1), row["distance_m"], row["visible_fraction"],
                   bool(row["truncated"]))


@dataclass(frozen=True, slots=True)
class RecordedDetection:
    """A detection as recorded: pixel box, confidence, and its localised nearest point in the ego frame [m]
    (None when the system did not localise it)."""

    box_xyxy: tuple[float, float, float, float]
    score: float
    position: tuple[float, float, float] | None = None

    def to_row(self) -> dict[str, Any]:
        return {"box_xyxy": list(self.box_xyxy), "score": self.score,
                "position": None if self.position is None else list(self.position)}

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> RecordedDetection:
        x0, y0, x1, y1 = row["box_xyxy"]
        pos = row.get("position")
        return cls((x0, y0, x1, y1), row["score"], None if pos is None else (pos[0], pos[1], pos[2]))


@dataclass(frozen=True, slots=True)
class EgoStep:
    """The ego after the tick: speed [m/s], the control the system chose for the next tick, its state."""

    speed: float
    throttle: float
    brake: float
    steer: float
    status: str


@dataclass(frozen=True, slots=True)
class LeadStep:
    """The vehicle ahead in the ego's path (``vehicle_id`` -1 and NaNs when there is none): the true bumper
    gap [m], its speed [m/s], the gap the system perceives [m] (NaN: it perceives none), and whether a
    detection matched its box (None when it is not in the image)."""

    vehicle_id: int
    true_distance: float
    speed: float
    perceived_distance: float
    detected: bool | None

    @property
    def present(self) -> bool:
        return self.vehicle_id >= 0


@dataclass(frozen=True, slots=True)
class PerceptionStep:
    """The frame's ground truth and the system's detections, with the frame IoU the reward reads."""

    n_detections: int
    n_in_view: int
    iou: float
    detections: tuple[RecordedDetection, ...]
    gt_boxes: tuple[RecordedBox, ...]


@dataclass(frozen=True, slots=True)
class CollisionStep:
    """The ego's collision in this tick: whether it hit, its speed at impact [m/s], the other vehicle."""

    collided: bool
    speed: float
    other_id: int


#: The flat columns before the knobs, in the order genesis-rl has always written them.
BASE_COLUMNS = ("step", "time_s", "ego_speed", "throttle", "brake", "steer", "status", "lead_id",
                "true_lead_distance", "lead_speed", "perceived_lead_distance", "n_detections", "n_in_view", "iou",
                "lead_detected", "collision", "collision_speed", "collision_with", "detections", "gt_boxes")
#: The conditions columns (``odd.conditions``) and the step's ODD label, after the knobs (genesis-rl 0.6.0 on).
CONDITION_COLUMNS = ("visibility_m", "rain_mm_h", "road_state", "light", "sun_glare", "odd_status")
#: The prefix of rule-term columns (``rule_collision``); reward terms are ``reward*`` columns.
RULE_PREFIX = "rule_"
REWARD_PREFIX = "reward"


@dataclass(frozen=True, slots=True)
class StepRecord:
    """One step (see the module docstring). ``knobs`` holds every knob of the weather set before the tick
    (the backend's whole knob set, in declaration order); ``rules`` the rulebook's per-step terms by rule
    name (empty until the rulebook scored the step); ``reward`` the reward's terms by name."""

    step: int
    time_s: float
    ego: EgoStep
    lead: LeadStep
    perception: PerceptionStep
    collision: CollisionStep
    knobs: Mapping[str, float]
    rules: Mapping[str, float] = field(default_factory=dict)
    reward: Mapping[str, float] = field(default_factory=dict)
    conditions: Conditions | None = None
    odd_status: str | None = None

    @property
    def iou(self) -> float:
        return self.perception.iou

    def scored(self, rules: Mapping[str, float], reward: Mapping[str, float] | None = None) -> StepRecord:
        """This step with the rulebook's terms (and the reward's) attached."""
        return replace(self, rules=dict(rules), reward=dict(reward or {}))

    def to_row(self) -> dict[str, Any]:
        """The flat telemetry row (the Parquet columns): base columns, knobs, ``rule_*``, reward terms."""
        e, lead, p, c = self.ego, self.lead, self.perception, self.collision
        row: dict[str, Any] = {
            "step": self.step, "time_s": self.time_s, "ego_speed": e.speed, "throttle": e.throttle,
            "brake": e.brake, "steer": e.steer, "status": e.status, "lead_id": lead.vehicle_id,
            "true_lead_distance": lead.true_distance, "lead_speed": lead.speed,
            "perceived_lead_distance": lead.perceived_distance, "n_detections": p.n_detections,
            "n_in_view": p.n_in_view, "iou": p.iou, "lead_detected": lead.detected, "collision": c.collided,
            "collision_speed": c.speed, "collision_with": c.other_id,
            "detections": [d.to_row() for d in p.detections], "gt_boxes": [b.to_row() for b in p.gt_boxes],
        }
        row.update(self.knobs)
        if self.conditions is not None:
            row.update(self.conditions.as_dict())
            row["odd_status"] = self.odd_status
        row.update({RULE_PREFIX + k: v for k, v in self.rules.items()})
        row.update(self.reward)
        return row

    @classmethod
    def from_row(cls, row: Mapping[str, Any], knob_names: Iterable[str] | None = None) -> StepRecord:
        """A record from a telemetry row (Parquet, JSON). ``knob_names``: the knob columns to read (default:
        every column that is not a base, rule or reward column)."""
        if knob_names is None:
            knob_names = [k for k in row if k not in _BASE_SET and k not in CONDITION_COLUMNS
                          and not k.startswith((RULE_PREFIX, REWARD_PREFIX))]
        conditions = None
        if row.get("visibility_m") is not None:
            conditions = Conditions(row["visibility_m"], row["rain_mm_h"], row["road_state"], row["light"],
                                    bool(row["sun_glare"]))
        return cls(
            step=int(row["step"]), time_s=row["time_s"],
            ego=EgoStep(row["ego_speed"], row["throttle"], row["brake"], row["steer"], row["status"]),
            lead=LeadStep(int(row["lead_id"]), _num(row["true_lead_distance"]), _num(row["lead_speed"]),
                          _num(row["perceived_lead_distance"]), row["lead_detected"]),
            perception=PerceptionStep(int(row["n_detections"]), int(row["n_in_view"]), row["iou"],
                                      tuple(RecordedDetection.from_row(d) for d in row["detections"]),
                                      tuple(RecordedBox.from_row(b) for b in row["gt_boxes"])),
            collision=CollisionStep(bool(row["collision"]), row["collision_speed"], int(row["collision_with"])),
            knobs={k: row[k] for k in knob_names if k in row},
            rules={k[len(RULE_PREFIX):]: v for k, v in row.items() if k.startswith(RULE_PREFIX)},
            reward={k: v for k, v in row.items() if k.startswith(REWARD_PREFIX)},
            conditions=conditions, odd_status=row.get("odd_status"),
        )


_BASE_SET = frozenset(BASE_COLUMNS)


def _num(v: Any) -> float:
    """A gap or speed column: JSON and Parquet write a missing value as null; the record keeps NaN."""
    return math.nan if v is None else v


def to_rows(records: Sequence[StepRecord]) -> list[dict[str, Any]]:
    return [r.to_row() for r in records]


def from_rows(rows: Iterable[Mapping[str, Any]]) -> list[StepRecord]:
    return [StepRecord.from_row(r) for r in rows]


def rule_column(name: str) -> str:
    """The telemetry column of a rule's per-step term."""
    return RULE_PREFIX + name


def synthetic_step(step: int = 0, *, ego_speed: float = 10.0, lead_gap: float = math.nan,
                   lead_speed: float = math.nan, collision: bool = False, collision_speed: float = 0.0,
                   iou: float = 1.0, knobs: Mapping[str, float] | None = None, dt: float = 0.05) -> StepRecord:
    """A hand-made step record, for testing a rule or a reward without a simulator (as the package's own
    tests do): the ego at ``ego_speed``, a lead ``lead_gap`` metres ahead (NaN: none), optionally colliding."""
    has_lead = math.isfinite(lead_gap)
    return StepRecord(
        step=step, time_s=round(step * dt, 3),
        ego=EgoStep(ego_speed, 0.0, 0.0, 0.0, "synthetic"),
        lead=LeadStep(1 if has_lead else -1, lead_gap, lead_speed, math.nan, None),
        perception=PerceptionStep(0, 0, iou, (), ()),
        collision=CollisionStep(collision, collision_speed if collision else 0.0, 1 if collision else -1),
        knobs=dict(knobs or {}),
    )
