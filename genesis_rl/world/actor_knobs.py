"""Actor knobs: other road users' behaviour as named, ranged, rate-limited knobs.

Declared like the weather knobs (one :class:`ActorKnobSpec` each, ``register_actor_knob`` for one's own),
but kept in their own registry so that every existing weather, record and episode stays exactly as it was:
a weather-only knob set never sees them. Each knob carries its physical unit, its range, a natural rate
(the largest change per simulated second, so the limit holds at any step length) and the source of its
range; "assumed" marks the values chosen here without a source.

Sources: UN R157 (cut-in a careful driver handles: relative speed 10..60 km/h ->
time-to-collision 0.48..1.64 s), Euro NCAP CCRb (lead braking at 2 or 6 m/s^2), highD/NGSIM (naturalistic
braking and accepted gaps), CARLA TrafficManager (per-vehicle parameter names and meanings).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError

#: a cut-in is made into the gap ``cut_in_ttc`` asks for, at most this much time-to-collision [s] below it
#: (the gap closes by one step's worth each step; a knob lowered past a gap does not cut into it)
CUT_IN_TTC_WINDOW = 0.25
#: UN R157 Annex 4 Appendix 3's lateral wandering distance [m]: a careful driver can perceive a cut-in once the
#: cutter has moved this far toward the ego's lane
CUT_IN_WANDER_M = 0.375
#: how long [s] after a cut-in's onset a careful driver can perceive it (the cutter has wandered ``CUT_IN_WANDER_M``):
#: lite's lane change, median of the 38 cut-ins of docs/results/11-cut-ins-r157.md (quartiles 0.25 and 0.35 s). A
#: cut-in starts this much before its gap closes to the ``cut_in_ttc`` asked, so that the knob is R157's
#: time-to-collision, taken at the perceivable moment, not at the onset
CUT_IN_PERCEIVE_AFTER_S = 0.3
#: a neighbour that ``cut_in_relative_speed`` slows keeps at least this share of its own target speed (lite) or
#: of its speed limit (CARLA): it gets ready by slowing, not by stopping beside a slow ego
CUT_IN_SPEED_FLOOR = 0.5
#: how far ahead [m] a neighbour may be to get ready for a cut-in (lite's leader range)
CUT_IN_PREPARE_RANGE_M = 80.0


@dataclass(frozen=True)
class ActorKnobSpec:
    """One actor parameter: range, unit, default (the actor does nothing unusual at it), natural rate
    [unit/s], the CARLA TrafficManager call it maps to (None: per-actor control, not yet mapped) and the
    source of its range."""

    name: str
    low: float
    high: float
    unit: str
    default: float
    natural_rate: float
    description: str = ""
    source: str = "assumed"
    carla_name: str | None = None

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise UserInputError(f"actor knob name {self.name!r} must be an identifier, e.g. lead_decel")
        for end in ("low", "high", "default"):
            ranges.number(getattr(self, end), f"actor knob '{self.name}': {end}", -1e9, 1e9, self.unit)
        if not self.low < self.high:
            raise UserInputError(f"actor knob '{self.name}': range {self.low}..{self.high} needs low < high")
        if not self.low <= self.default <= self.high:
            raise UserInputError(f"actor knob '{self.name}': default {self.default} is outside "
                                 f"{self.low:g}..{self.high:g}")
        ranges.number(self.natural_rate, f"actor knob '{self.name}': natural_rate", 1e-9, 1e9, f"{self.unit}/s")


def _a(name: str, low: float, high: float, unit: str, default: float, rate: float, desc: str, source: str,
       carla: str | None = None) -> ActorKnobSpec:
    return ActorKnobSpec(name, low, high, unit, default, rate, desc, source, carla)


_TM = "CARLA TrafficManager per-vehicle parameter"
#: The built-in actor knobs. Ranges of lead braking and cut-in come from the sources named; rates are assumed.
ACTOR_KNOBS: dict[str, ActorKnobSpec] = {
    k.name: k
    for k in (
        _a("lead_decel", 0.0, 8.0, "m/s^2", 0.0, 4.0,
           "deceleration the lead vehicle demands while braking (0: no braking)",
           "Euro NCAP CCRb brakes at 2 and 6 m/s^2; 8 m/s^2 is near dry-road friction (assumed); "
           "highD/NGSIM braking distributions to refine it. Rate assumed (jerk-like, 4 m/s^2 per s)"),
        _a("lead_brake_onset", 0.0, 30.0, "s", 30.0, 1.0,
           "episode time at which the lead starts braking (30: never within a default episode)",
           "assumed; rate 1 s/s so an onset cannot be pulled earlier faster than time passes"),
        _a("cut_in_ttc", 0.4, 10.0, "s", 10.0, 0.5,
           "time-to-collision of the gap a neighbour cuts into (ego's speed minus the cutter's, over the gap), "
           "when the cut-in becomes perceivable (the cutter 0.375 m across: R157's measure)",
           "UN R157: 0.48/0.71/0.94/1.18/1.41/1.64 s at 10..60 km/h relative speed is what a careful driver "
           "handles; 0.4 s lower bound and 10 s default (a harmless cut-in) assumed; rate assumed"),
        _a("cut_in_relative_speed", 0.0, 20.0, "m/s", 0.0, 1.0,
           "how much slower than the ego the neighbour a cut-in is asked of drives as it gets ready (0: at its own "
           "pace, so only the traffic supplies a closing gap)",
           "UN R157 Annex 4 Appendix 3: cut-ins at 10..60 km/h (2.8..16.7 m/s) relative speed; 20 m/s upper bound "
           "and rate (1 m/s per s) assumed"),
        _a("cut_in_onset", 0.0, 30.0, "s", 30.0, 1.0,
           "episode time at which the neighbour starts its lane change (30: never within a default episode)",
           "assumed"),
        _a("distance_to_leading_vehicle", 0.5, 30.0, "m", 5.0, 1.0,
           "standstill gap each NPC keeps to its leader (IDM's s0)", f"{_TM}; range and rate assumed",
           "distance_to_leading_vehicle"),
        _a("vehicle_percentage_speed_difference", -50.0, 100.0, "%", 0.0, 2.0,
           "how much slower than its target speed an NPC drives (negative: faster)",
           f"{_TM}; range and rate assumed", "vehicle_percentage_speed_difference"),
        _a("ignore_lights_percentage", 0.0, 100.0, "%", 0.0, 1.0,
           "chance an NPC runs a red light", f"{_TM}; rate assumed", "ignore_lights_percentage"),
        _a("auto_lane_change", 0.0, 1.0, "", 1.0, 0.1,
           "whether NPCs may change lanes on their own (>= 0.5: on)", f"{_TM} (a bool here as 0/1)",
           "auto_lane_change"),
        _a("random_left_lanechange_percentage", 0.0, 100.0, "%", 0.0, 1.0,
           "chance per second an NPC changes to its left lane unprompted", f"{_TM}; rate assumed",
           "random_left_lanechange_percentage"),
        _a("random_right_lanechange_percentage", 0.0, 100.0, "%", 0.0, 1.0,
           "chance per second an NPC changes to its right lane unprompted", f"{_TM}; rate assumed",
           "random_right_lanechange_percentage"),
    )
}

#: the module that declared each knob added with ``register_actor_knob``
ACTOR_KNOB_MODULES: dict[str, str] = {}


def register_actor_knob(spec: ActorKnobSpec) -> ActorKnobSpec:
    """Declare an actor knob of one's own (in one's module, at import), the way ``register_knob`` does
    for weather."""
    if spec.name in ACTOR_KNOBS and ACTOR_KNOBS[spec.name] != spec:
        raise UserInputError(f"actor knob '{spec.name}' is already declared ({ACTOR_KNOBS[spec.name].description!r})")
    ACTOR_KNOBS[spec.name] = spec
    ACTOR_KNOB_MODULES[spec.name] = sys._getframe(1).f_globals.get("__name__", "")
    return spec


def actor_knob_spec(name: str) -> ActorKnobSpec:
    try:
        return ACTOR_KNOBS[name]
    except KeyError:
        raise UserInputError(f"unknown actor knob '{name}'; allowed: {', '.join(ACTOR_KNOBS)}") from None


def is_actor_knob(name: str) -> bool:
    return name in ACTOR_KNOBS


def actor_max_deltas(knobs: Sequence[str], dt: float) -> np.ndarray:
    """Largest change of each knob over a step of ``dt`` seconds: its natural rate times ``dt``."""
    ranges.number(dt, "dt", 1e-6, 60.0, "s")
    return np.array([actor_knob_spec(k).natural_rate * dt for k in knobs], dtype=np.float64)


def limit_step(before: Mapping[str, float], wanted: Mapping[str, float], dt: float) -> dict[str, float]:
    """Move each knob from ``before`` toward ``wanted`` by at most its natural rate times ``dt``, within range."""
    out: dict[str, float] = {}
    for name, target in wanted.items():
        spec = actor_knob_spec(name)
        step = spec.natural_rate * dt
        value = before[name] + float(np.clip(target - before[name], -step, step))
        out[name] = float(np.clip(value, spec.low, spec.high))
    return out


@dataclass(frozen=True)
class TrafficConditions:
    """What an ODD releases the system for in traffic: the strongest lead deceleration [m/s^2], the
    shortest cut-in time-to-collision [s] and the largest relative speed of a cut-in [m/s]. Defaults release
    nothing unusual beyond R157's careful driver."""

    max_lead_decel: float = 6.0  # Euro NCAP CCRb's hard case
    min_cut_in_ttc: float = 1.64  # UN R157 at 60 km/h relative speed (the longest of its boundary TTCs)
    max_cut_in_relative_speed: float = 60.0 / 3.6  # UN R157's fastest cut-in: 60 km/h relative speed

    def violations(self, values: Mapping[str, float]) -> list[str]:
        """The actor knob values beyond these conditions, each with its bound (empty: inside; knobs not given
        count as their default)."""
        decel = float(values.get("lead_decel", ACTOR_KNOBS["lead_decel"].default))
        ttc = float(values.get("cut_in_ttc", ACTOR_KNOBS["cut_in_ttc"].default))
        rel = float(values.get("cut_in_relative_speed", ACTOR_KNOBS["cut_in_relative_speed"].default))
        out = []
        if decel > self.max_lead_decel:
            out.append(f"lead_decel {decel:g} m/s^2 > {self.max_lead_decel:g}")
        if ttc < self.min_cut_in_ttc:
            out.append(f"cut_in_ttc {ttc:g} s < {self.min_cut_in_ttc:g}")
        if rel > self.max_cut_in_relative_speed + 1e-9:
            out.append(f"cut_in_relative_speed {rel:g} m/s > {self.max_cut_in_relative_speed:g}")
        return out

    def contains(self, values: Mapping[str, float]) -> bool:
        """Whether actor knob values lie inside these conditions (knobs not given count as their default)."""
        return not self.violations(values)


TRAFFIC_FIELDS = ("max_lead_decel", "min_cut_in_ttc", "max_cut_in_relative_speed")


def parse_traffic_conditions(table: object, where: str = "odd.traffic") -> TrafficConditions:
    """Read an ODD file's ``[traffic]`` table; a bad value or unknown field is refused naming it."""
    if not isinstance(table, Mapping):
        raise UserInputError(f"{where} must be a table with {', '.join(TRAFFIC_FIELDS)}")
    unknown = sorted(set(table) - set(TRAFFIC_FIELDS))
    if unknown:
        raise UserInputError(f"{where}: unknown field(s) {unknown}; allowed: {', '.join(TRAFFIC_FIELDS)}")
    base = TrafficConditions()
    decel = ranges.number(table.get("max_lead_decel", base.max_lead_decel), f"{where}.max_lead_decel",
                          0.0, ACTOR_KNOBS["lead_decel"].high, "m/s^2")
    ttc = ranges.number(table.get("min_cut_in_ttc", base.min_cut_in_ttc), f"{where}.min_cut_in_ttc",
                        ACTOR_KNOBS["cut_in_ttc"].low, ACTOR_KNOBS["cut_in_ttc"].high, "s")
    rel = ranges.number(table.get("max_cut_in_relative_speed", base.max_cut_in_relative_speed),
                        f"{where}.max_cut_in_relative_speed", 0.0, ACTOR_KNOBS["cut_in_relative_speed"].high, "m/s")
    return TrafficConditions(float(decel), float(ttc), float(rel))


def pick_cut_in(candidates: Iterable[tuple[int, float, float]], ttc: float) -> tuple[int, float, float] | None:
    """The vehicle to cut in for the ``cut_in_ttc`` knob at ``ttc``, from (vehicle, bumper gap [m], closing
    speed [m/s]) of the vehicles ahead in the ego's neighbouring lanes: the nearest whose time-to-collision
    once the cut-in is perceivable (``CUT_IN_PERCEIVE_AFTER_S`` from now, at today's closing speed: R157's
    measure) lies within ``CUT_IN_TTC_WINDOW`` below ``ttc`` seconds (more than 1 m of gap, closing faster
    than 0.5 m/s). One rule for every backend: lite's traffic and CARLA's traffic manager cut in the same
    vehicle."""
    best: tuple[int, float, float] | None = None
    for vehicle, gap, closing in candidates:
        if gap <= 1.0 or closing <= 0.5:
            continue
        seen = gap / closing - CUT_IN_PERCEIVE_AFTER_S
        if ttc - CUT_IN_TTC_WINDOW <= seen <= ttc and (best is None or gap < best[1]):
            best = (int(vehicle), float(gap), float(closing))
    return best


def pick_preparing(gaps: Mapping[int, float], current: int) -> int:
    """The neighbour that gets ready for a cut-in (``cut_in_relative_speed``), from the bumper gap [m] of each
    vehicle ahead in the ego's neighbouring lanes: ``current`` while it is still ahead within
    ``CUT_IN_PREPARE_RANGE_M``, else the nearest that is (-1: nobody). One rule for every backend."""
    ahead = {j: gap for j, gap in gaps.items() if 1.0 < gap < CUT_IN_PREPARE_RANGE_M}
    if current in ahead:
        return current
    return min(ahead, key=ahead.__getitem__) if ahead else -1


def preparing_speed(ego_speed: float, relative_speed: float, own_speed: float) -> float:
    """The speed [m/s] a neighbour getting ready slows to: ``relative_speed`` under the ego's, never under
    ``CUT_IN_SPEED_FLOOR`` of ``own_speed`` (lite: its target speed; CARLA: its speed limit)."""
    return max(CUT_IN_SPEED_FLOOR * own_speed, ego_speed - relative_speed)


def cut_in_gap(ego_speed: float, cutter_speed: float, ttc: float) -> float:
    """The gap [m] a cut-in at time-to-collision ``ttc`` leaves ahead of the ego (inf if it is not closing)."""
    closing = ego_speed - cutter_speed
    return ttc * closing if closing > 0 else math.inf
