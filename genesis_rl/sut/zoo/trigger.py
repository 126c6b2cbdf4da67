"""A zoo member's trigger region: where its weakness lies, in physical units, stated before any adversary runs.

A benchmark can only say an adversary *reached* a weakness and then *triggered* it (Magma's canaries) when the
weakness is written down as a region a step is in or not. A region is a conjunction of half-open bounds
``low <= value < high`` on weather knobs (``sun_altitude_angle`` in deg, ``fog_density`` in %, the actor knob
``lead_decel`` in m/s^2, ...) and on the step's numeric conditions (``visibility_m``, ``rain_mm_h``, which
records carry when an ODD was declared), or on a step's flag condition (``sun_glare``: the sun low in the camera's
view, which depends on where the camera looks, so only a step can say). Half-open, so regions tile as the AMS
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
_CONDITIONS = (*CONDITION_UNITS, *CONDITION_FLAGS)


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
        if self.quantity in CONDITION_FLAGS:
            return ""
        return CONDITION_UNITS.get(self.quantity) or KNOBS[self.quantity].unit

    def holds(self, rec: StepRecord) -> bool:
        if self.is_condition:
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
        if self.quantity in CONDITION_FLAGS:
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

    def contains(self, rec: StepRecord) -> bool:
        return bool(self.bounds) and all(b.holds(rec) for b in self.bounds)

    def reached(self, records: Sequence[StepRecord]) -> int | None:
        """The index of the first step inside the region (None: the episode never entered it)."""
        return next((i for i, rec in enumerate(records) if self.contains(rec)), None)

    def describe(self) -> str:
        if self.empty:
            return "empty (a control: no in-ODD weakness to find)"
        return " and ".join(b.describe() for b in self.bounds)


#: a control's region
EMPTY = TriggerRegion()
