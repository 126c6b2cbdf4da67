"""Numbers checked where they enter: type, finiteness and a physical range with its unit.

A number read from a file or a flag is believed only inside a range that is physical and generous (a speed
in 0..70 m/s, a deceleration in 0.1..30 m/s^2), so that no later arithmetic overflows, divides by a
subnormal or freezes: ``1e-320`` as a deceleration, ``1e308`` as a weight or ``1e200`` as a speed are refused
here, naming the field, instead of turning into ``inf`` or an ``OverflowError`` steps later.

    >>> SPEED.check(1000.0, "scene 3 lead speed")
    Traceback (most recent call last):
    ...
    genesis_rl.core.errors.UserInputError: scene 3 lead speed = 1000.0 must be in 0..70 m/s (a finite number)

``bool`` is not a number (``true`` in a file is refused where a number is expected); an integer field takes
an ``int`` only; a float field takes ``int`` or ``float``. docs/reliability/numbers.md lists every field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from genesis_rl.core.errors import UserInputError


def fmt(x: float) -> str:
    """A bound as a person writes it: 70, 0.1, 1e+06, 65535."""
    if isinstance(x, int) or (math.isfinite(x) and x == int(x) and abs(x) < 1e6):
        return str(int(x))
    return f"{x:g}"


@dataclass(frozen=True)
class Ranged:
    """A closed range ``[low, high]`` in ``unit``; ``integer`` fields take ints only. Both bounds are finite
    and small enough that sums and products of a few values stay finite in float64."""

    low: float
    high: float
    unit: str = ""
    integer: bool = False
    note: str = ""  # why the range, for the docs and the message (e.g. "CNN policies need >= 36")

    def bounds(self) -> str:
        """``low..high``, as a person writes the bounds."""
        return f"{fmt(self.low)}..{fmt(self.high)}"

    def describe(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        kind = "an integer" if self.integer else "a number"
        return f"{kind} in {self.bounds()}{unit}"

    def check(self, value: Any, field: str) -> Any:
        """``value`` as an int (integer fields) or a float, or a :class:`UserInputError` naming ``field``."""
        return number(value, field, self.low, self.high, self.unit, integer=self.integer, note=self.note)


def number(value: Any, field: str, low: float, high: float, unit: str = "", *, integer: bool = False,
           note: str = "") -> Any:
    """Check that ``value`` (of ``field``, e.g. ``env.camera_width`` or ``--carla-timeout``) is a number of the
    right type, finite and within ``[low, high]`` ``unit``; return it as ``int`` or ``float``. The message
    reads ``env.obs_history = 0 must be in 1..16 steps (an integer)``."""
    # the common case first, before any message is built: a catalog checks a million numbers on load
    kind_of = type(value)
    if kind_of is float and not integer and low <= value <= high and math.isfinite(value):
        return value
    if kind_of is int and low <= value <= high:
        return value if integer else float(value)
    unit_s = f" {unit}" if unit else ""
    kind = "an integer" if integer else "a finite number"
    allowed = f"must be in {fmt(low)}..{fmt(high)}{unit_s} ({kind}" + (f"; {note})" if note else ")")
    if isinstance(value, bool) or not isinstance(value, int | float) or (integer and not isinstance(value, int)):
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        raise UserInputError(f"{field} = {shown} ({type(value).__name__}) {allowed}")
    if isinstance(value, int):
        if not low <= value <= high:  # exact for ints of any size (a JSON integer may have 400 digits)
            shown = str(value) if len(str(value)) <= 30 else f"{str(value)[:12]}...({len(str(value))} digits)"
            raise UserInputError(f"{field} = {shown} {allowed}")
        return value if integer else float(value)
    if not math.isfinite(value) or not low <= value <= high:
        raise UserInputError(f"{field} = {value!r} {allowed}")
    return float(value)


def check_type(value: Any, field: str, rng: Ranged) -> None:
    """The type half of :meth:`Ranged.check` (an int for integer fields, else an int or a float; never a bool),
    for loaders that compare a value with their own messages before its range is checked."""
    if isinstance(value, bool) or not isinstance(value, int | float) or (rng.integer and not isinstance(value, int)):
        number(value, field, rng.low, rng.high, rng.unit, integer=rng.integer, note=rng.note)


def generic(value: Any, field: str, magnitude: float = 1e9) -> float:
    """A number without a declared physical range (a plug-in rule's parameter): finite, and 0 or of a
    magnitude in [1/magnitude, magnitude], so that dividing by it or multiplying with it stays finite."""
    x = number(value, field, -magnitude, magnitude)
    if x != 0.0 and abs(x) < 1.0 / magnitude:
        raise UserInputError(f"{field} = {x!r} must be 0 or of magnitude in {1.0 / magnitude:g}..{magnitude:g}")
    return x


# -- ranges shared by several loaders (units in the names' comments) -------------------------------------------
SPEED = Ranged(0.0, 70.0, "m/s")  # 252 km/h: above every road's limit and every make's top speed (<= 50 m/s)
ACCEL = Ranged(1e-3, 15.0, "m/s^2")  # an autopilot's maximum acceleration; 15 m/s^2 is 1.5 g
DECEL = Ranged(0.1, 30.0, "m/s^2")  # a braking deceleration; 1 g = 9.81 m/s^2, racing cars reach ~3 g
DISTANCE = Ranged(0.0, 1000.0, "m")  # a gap, threshold or following distance
COORDINATE = Ranged(-100_000.0, 100_000.0, "m")  # a map position: 100 km from the map's origin
ARC_LENGTH = Ranged(0.0, 1_000_000.0, "m")  # a position along a lane (a backend checks its lane's length)
YAW = Ranged(-2 * math.pi, 2 * math.pi, "rad")
DURATION = Ranged(0.0, 3600.0, "s")
SIGNAL_OFFSET = Ranged(-86_400.0, 86_400.0, "s")  # one day either way
WEIGHT = Ranged(0.0, 1e6, "")  # a reward weight; 1e6 x a 70 m/s term stays far from overflow
FRACTION = Ranged(0.0, 1.0, "")
PORT = Ranged(1, 65535, "", integer=True)
TIMEOUT = Ranged(0.1, 3600.0, "s")  # a network timeout
SEED = Ranged(0, 2**63 - 1, "", integer=True)  # numpy's and TOML's 64-bit integers
