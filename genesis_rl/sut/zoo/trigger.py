"""A zoo member's trigger region: where its weakness lies, in physical units, stated before any adversary runs.

A benchmark can only say an adversary *reached* a weakness and then *triggered* it (Magma's canaries) when the
weakness is written down as a region a step is in or not. A region is a conjunction of half-open bounds
``low <= value < high`` on weather knobs (``sun_altitude_angle`` in deg, ``fog_density`` in %, the actor knob
``lead_decel`` in m/s^2, ...) and on the step's numeric conditions (``visibility_m``, ``rain_mm_h``, which
records carry when an ODD was declared), or on a step's flag condition (``sun_glare``: the sun low in the camera's
view, which depends on where the camera looks, so only a step can say), or on what the system did over the last
steps (``stale_frames``: its detections repeated exactly within the last :data:`STALE_HOLD_S`, as a stalling
camera's do; only the episode's sequence can say). Half-open, so regions tile as the AMS
rain categories do. A region with no bounds is *empty*: a control's, on which there is nothing to find.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from genesis_rl.core.errors import UserInputError
from genesis_rl.world.knobs import KNOBS
from genesis_rl.world.step_record import StepRecord

#: the numeric conditions a bound may name, with their units (``odd.conditions.Conditions``)
CONDITION_UNITS = {"visibility_m": "m", "rain_mm_h": "mm/h"}
#: the flag conditions a bound may name (``Bound.flag``): value 1 while set, 0 while clear
CONDITION_FLAGS = ("sun_glare",)
#: flags that only the episode's sequence of steps can set (``stale_frames``, see :func:`stale_frames`)
SEQUENCE_FLAGS = ("stale_frames",)
#: a step is ``stale_frames`` when the system's detections repeated exactly at it or within this many seconds
#: before it (a stutter repeats every other frame; the flag stays set between its repeats)
STALE_HOLD_S = 0.5
_CONDITIONS = (*CONDITION_UNITS, *CONDITION_FLAGS, *SEQUENCE_FLAGS)


def stale_frames(records: Sequence[StepRecord]) -> list[bool]:
    """Per step: whether the system's detections (non-empty) repeated exactly at it or in the
    :data:`STALE_HOLD_S` before it, as they do when a camera re-delivers its last frame."""
    out: list[bool] = []
    last_repeat = -math.inf
    for i, rec in enumerate(records):
        dets = rec.perception.detections
        if i and dets and dets == records[i - 1].perception.detections:
            last_repeat = rec.time_s
        out.append(rec.time_s - last_repeat <= STALE_HOLD_S + 1e-9)
    return out


@dataclass(frozen=True)
class Bound:
    """``low <= quantity < high``; ``quantity`` a knob name or a numeric condition (CONDITION_UNITS)."""

    quantity: str
    low: float = -math.inf
    high: float = math.inf

    def __post_init__(self) -> None:
        if self.quantity not in KNOBS and self.quantity not in _CONDITIONS:
            raise UserInputError(f"trigger bound quantity = '{self.quantity}' is unknown; allowed: a knob "
                                 f"({', '.join(KNOBS)}) or a condition ({', '.join(_CONDITIONS)})")
        if math.isnan(self.low) or math.isnan(self.high) or not self.low < self.high:
            raise UserInputError(f"trigger bound on {self.quantity}: low {self.low:g} must be below high "
                                 f"{self.high:g} (the bound is low <= value < high)")

    @classmethod
    def flag(cls, quantity: str, is_set: bool = True) -> Bound:
        """A bound that holds while the flag condition ``quantity`` is set (or, ``is_set=False``, clear)."""
        return cls(quantity, 0.5, math.inf) if is_set else cls(quantity, -math.inf, 0.5)

    @property
    def is_condition(self) -> bool:
        """Whether the bound reads a step's conditions (numeric or flag) rather than its knobs."""
        return self.quantity in _CONDITIONS

    @property
    def unit(self) -> str:
        if self.quantity in CONDITION_FLAGS or self.quantity in SEQUENCE_FLAGS:
            return ""
        return CONDITION_UNITS.get(self.quantity) or KNOBS[self.quantity].unit

    def holds(self, rec: StepRecord, stale: bool = False) -> bool:
        """Whether ``rec`` is inside the bound; ``stale``: the step's ``stale_frames`` flag (sequence flags
        cannot be read from one step)."""
        if self.quantity in SEQUENCE_FLAGS:
            value = float(stale)
        elif self.is_condition:
            if rec.conditions is None:
                raise UserInputError(f"the trigger region bounds {self.quantity}, but step {rec.step} carries no "
                                     "conditions: run the campaign with an ODD (env.odd)")
            value = float(getattr(rec.conditions, self.quantity))
        else:
            if self.quantity not in rec.knobs:  # a record from before the knob existed: it sat at its default
                value = float(KNOBS[self.quantity].default)
            else:
                value = float(rec.knobs[self.quantity])
        return self.low <= value < self.high

    def describe(self) -> str:
        if self.quantity in CONDITION_FLAGS or self.quantity in SEQUENCE_FLAGS:
            return self.quantity if self.low > 0.0 else f"no {self.quantity}"
        unit = f" {self.unit}" if self.unit else ""
        if math.isinf(self.low):
            return f"{self.quantity} < {self.high:g}{unit}"
        if math.isinf(self.high):
            return f"{self.quantity} >= {self.low:g}{unit}"
        return f"{self.low:g} <= {self.quantity} < {self.high:g}{unit}"


@dataclass(frozen=True)
class TriggerRegion:
    """Every bound holds (a conjunction); no bounds: the empty region of a control."""

    bounds: tuple[Bound, ...] = ()

    @property
    def empty(self) -> bool:
        return not self.bounds

    @property
    def needs_sequence(self) -> bool:
        """Whether a bound reads a sequence flag: then only ``reached`` over the episode can tell."""
        return any(b.quantity in SEQUENCE_FLAGS for b in self.bounds)

    def contains(self, rec: StepRecord, stale: bool = False) -> bool:
        return bool(self.bounds) and all(b.holds(rec, stale) for b in self.bounds)

    def reached(self, records: Sequence[StepRecord]) -> int | None:
        """The index of the first step inside the region (None: the episode never entered it)."""
        stale = stale_frames(records) if self.needs_sequence else [False] * len(records)
        return next((i for i, rec in enumerate(records) if self.contains(rec, stale[i])), None)

    def describe(self) -> str:
        if self.empty:
            return "empty (a control: no in-ODD weakness to find)"
        return " and ".join(b.describe() for b in self.bounds)


#: a control's region
EMPTY = TriggerRegion()
