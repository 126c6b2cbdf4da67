"""An operational design domain (ODD) as a contract: the conditions a system claims to handle, in physical
units, read from a TOML file (``configs/odd/*.toml``; schema in docs/odd.md).

A declared ODD does three jobs. It *labels* every step: ``inside``, ``boundary`` (inside, but within
``boundary_margin`` of a numeric bound) or ``outside``. It *keeps* every weather policy inside: when a
policy's step would leave the domain, :meth:`ODD.keep_inside` moves the weather only as far toward the
policy's choice as the domain allows (a bisection per knob from the last weather, so a policy pushing
against a bound rides along it). And it is *checked* up front: unknown quantities, missing units,
empty domains and bounds the backend cannot show are refused, naming the field.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.world.actor_knobs import TrafficConditions, parse_traffic_conditions
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.odd.conditions import LIGHTS, ROAD_STATES, Conditions, ConditionsModel

#: numeric quantities: unit, and the Conditions field they bound
NUMERIC = {"visibility": ("m", "visibility_m"), "rain_rate": ("mm/h", "rain_mm_h")}
#: the physical range of each numeric quantity's bounds: visibility up to 100 km (a clear day's meteorological
#: range is tens of km); rain up to 2000 mm/h (record one-minute rates are below it)
NUMERIC_RANGES = {"visibility": ranges.Ranged(0.0, 100_000.0, "m"), "rain_rate": ranges.Ranged(0.0, 2000.0, "mm/h")}
#: categorical quantities: allowed values, and the Conditions field
CATEGORICAL = {"road_state": (ROAD_STATES, "road_state"), "light": (LIGHTS, "light")}
#: the sun's altitude [deg], bounded on the weather itself (its knob is already in degrees): a camera system may
#: be released for daylight with the sun at least so high, as a low sun's long shadows and colour are conditions
#: its data may lack (docs/zoo.md's low-sun members)
SUN_ALTITUDE = "sun_altitude"
SUN_ALTITUDE_RANGE = ranges.Ranged(-90.0, 90.0, "deg")
QUANTITIES = (*NUMERIC, *CATEGORICAL, "sun_glare", SUN_ALTITUDE)
STATUSES = ("inside", "boundary", "outside")
#: the labels a failure counts in: inside the domain, on its boundary included
IN_ODD = ("inside", "boundary")
_TOP_KEYS = {"name", "description", "boundary_margin", "traffic", *QUANTITIES}


@dataclass(frozen=True)
class Range:
    low: float = 0.0
    high: float = math.inf

    def contains(self, v: float) -> bool:
        return self.low <= v <= self.high

    def near_bound(self, v: float, margin: float) -> bool:
        """Within ``margin`` (a fraction of the bound) of a finite bound."""
        return (self.low > 0 and v < self.low * (1 + margin)) or \
            (math.isfinite(self.high) and v > self.high * (1 - margin))


@dataclass(frozen=True)
class ODD:
    """A domain: numeric ranges, allowed categories, whether sun glare is allowed."""

    name: str
    description: str = ""
    ranges: Mapping[str, Range] = field(default_factory=dict)  # by NUMERIC quantity
    allowed: Mapping[str, tuple[str, ...]] = field(default_factory=dict)  # by CATEGORICAL quantity
    sun_glare_allowed: bool = True
    boundary_margin: float = 0.1
    source: str = ""
    #: traffic conditions the system is released for; None: the file has no [traffic] table
    traffic: TrafficConditions | None = None
    #: the sun altitudes the system is released for [deg], checked on the weather; None: no [sun_altitude] table
    sun_altitude: tuple[float, float] | None = None

    # -- labelling -----------------------------------------------------------------------------------------
    def violations(self, c: Conditions, weather: Weather | None = None) -> list[str]:
        """The quantities of ``c`` outside the domain, each with its value and bound (empty: inside); with
        ``weather``, also its actor knobs against the traffic conditions (the file's ``[traffic]``, else
        :class:`TrafficConditions`' defaults: CCRb's 6 m/s^2, R157's 1.64 s)."""
        out = [] if weather is None else self.traffic_violations(weather)
        if weather is not None and self.sun_altitude is not None:
            alt, (low, high) = float(weather["sun_altitude_angle"]), self.sun_altitude
            if not low <= alt <= high:
                out.append(f"sun_altitude {alt:g} deg not in [{low:g}, {high:g}]")
        for q, r in self.ranges.items():
            v = getattr(c, NUMERIC[q][1])
            if not r.contains(v):
                out.append(f"{q} {v:g} {NUMERIC[q][0]} not in [{r.low:g}, {r.high:g}]")
        for q, allowed in self.allowed.items():
            v = getattr(c, CATEGORICAL[q][1])
            if v not in allowed:
                out.append(f"{q} '{v}' not in {list(allowed)}")
        if c.sun_glare and not self.sun_glare_allowed:
            out.append("sun_glare")
        return out

    def traffic_violations(self, weather: Weather) -> list[str]:
        """The actor knobs of ``weather`` beyond the traffic conditions the system is released for."""
        return (self.traffic or TrafficConditions()).violations(weather.values)

    def contains(self, c: Conditions, weather: Weather | None = None) -> bool:
        return not self.violations(c, weather)

    def status(self, c: Conditions, weather: Weather | None = None) -> str:
        if not self.contains(c, weather):
            return "outside"
        near = any(r.near_bound(getattr(c, NUMERIC[q][1]), self.boundary_margin) for q, r in self.ranges.items())
        return "boundary" if near else "inside"

    # -- keeping a policy inside ---------------------------------------------------------------------------
    def keep_inside(self, before: Weather, proposed: Weather, model: ConditionsModel,
                    heading_deg: float | None = None, iterations: int = 10) -> Weather:
        """``proposed`` if it is inside; else each knob, in declaration order, moves from ``before`` as far
        toward its proposed value as the domain allows (a bisection per knob), so a policy pushing fog
        against the visibility bound still turns the road wet. ``before`` is returned as it is when it is
        outside already (e.g. the road turned the camera into a low sun: no knob move undoes that)."""
        if self.contains(model.conditions(proposed, heading_deg), proposed):
            return proposed
        if not self.contains(model.conditions(before, heading_deg), before):
            return before
        best = before
        for name, spec in KNOBS.items():
            target = proposed[name]
            start = best[name]
            if target == start:
                continue
            delta = target - start
            if spec.wraps:  # the short way round, as the mapper moved it
                delta = (delta + spec.span / 2) % spec.span - spec.span / 2
            full = _with(best, name, start + delta)
            if self.contains(model.conditions(full, heading_deg), full):
                best = full
                continue
            # a knob held at its bound (the usual case when a policy pushes against it) costs one more look
            look = _with(best, name, start + _FIRST_LOOK * delta)
            if not self.contains(model.conditions(look, heading_deg), look):
                continue
            lo, hi = _FIRST_LOOK, 1.0
            for _ in range(iterations):
                mid = (lo + hi) / 2
                w = _with(best, name, start + mid * delta)
                if self.contains(model.conditions(w, heading_deg), w):
                    lo = mid
                else:
                    hi = mid
            if lo > 0:
                best = _with(best, name, start + lo * delta)
        return best

    def describe(self) -> dict[str, Any]:
        """The domain as data (campaigns and records store it)."""
        d: dict[str, Any] = {"name": self.name, "description": self.description,
                             "boundary_margin": self.boundary_margin}
        for q, r in self.ranges.items():
            d[q] = {k: v for k, v in (("min", r.low), ("max", r.high)) if math.isfinite(v) and (k == "max" or v > 0)} \
                | {"unit": NUMERIC[q][0]}
        for q, allowed in self.allowed.items():
            d[q] = {"allowed": list(allowed)}
        d["sun_glare"] = {"allowed": self.sun_glare_allowed}
        if self.sun_altitude is not None:  # likewise
            d[SUN_ALTITUDE] = {"min": self.sun_altitude[0], "max": self.sun_altitude[1], "unit": "deg"}
        if self.traffic is not None:  # only then, so domains without one describe as before
            d["traffic"] = {"max_lead_decel": self.traffic.max_lead_decel,
                            "min_cut_in_ttc": self.traffic.min_cut_in_ttc}
            base = TrafficConditions().max_cut_in_relative_speed
            if self.traffic.max_cut_in_relative_speed != base:  # likewise: campaigns before 0.24 resume
                d["traffic"]["max_cut_in_relative_speed"] = self.traffic.max_cut_in_relative_speed
        return d


#: the smallest share of a step a blocked knob is tried with before it is bisected
_FIRST_LOOK = 1.0 / 64.0


def _with(weather: Weather, name: str, value: float) -> Weather:
    """``weather`` with one knob set, wrapped or clipped to its range."""
    return Weather({**weather.values, name: float(KNOBS[name].fit(value))})


# -- reading a file ------------------------------------------------------------------------------------------
def _number(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise UserInputError(f"{where} = {value!r} must be a finite number")
    return float(value)


def _bounds(t: Any, q: str, where: str, unit: str, physical: ranges.Ranged,
            unbounded: tuple[float, float]) -> tuple[float, float]:
    """A ``[q] min = ..., max = ..., unit = "..."`` table's bounds, each given one inside ``physical``; a bound
    left out is ``unbounded``'s."""
    if not isinstance(t, Mapping):
        raise UserInputError(f"{where} must be a table, e.g. [{q}] min = ..., unit = \"{unit}\"")
    extra = set(t) - {"min", "max", "unit"}
    if extra:
        raise UserInputError(f"{where}: unknown key(s) {sorted(extra)}; allowed: min, max, unit")
    if "unit" not in t:
        raise UserInputError(f"{where}: unit is missing; allowed: unit = \"{unit}\"")
    if t["unit"] != unit:
        raise UserInputError(f"{where}: unit = {t['unit']!r}; allowed: \"{unit}\"")
    if "min" not in t and "max" not in t:
        raise UserInputError(f"{where}: give min, max or both [{unit}]")
    low = _number(f"{where}.min", t["min"]) if "min" in t else unbounded[0]
    high = _number(f"{where}.max", t["max"]) if "max" in t else unbounded[1]
    for end, v in (("min", low), ("max", high)):
        if end in t:
            physical.check(v, f"{where}.{end}")
    if low > high:
        raise UserInputError(f"{where}: min {low:g} > max {high:g}: the domain is empty")
    return low, high


def parse_odd(data: Mapping[str, Any], source: str, model: ConditionsModel | None = None) -> ODD:
    """An ODD from its TOML tables; ``model`` (the backend's) checks that its visibility bounds are reachable."""
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise UserInputError(f"ODD '{source}': unknown quantity or key(s) {sorted(unknown)}; allowed: "
                             f"{', '.join(QUANTITIES)} (and name, description, boundary_margin)")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str) or not name:
        raise UserInputError(f"ODD '{source}': name = {name!r} must be a non-empty string")
    margin = _number(f"ODD '{source}': boundary_margin", data.get("boundary_margin", 0.1))
    if not 0.0 <= margin < 1.0:
        raise UserInputError(f"ODD '{source}': boundary_margin = {margin} must be in [0, 1)")
    ranges: dict[str, Range] = {}
    for q, (unit, _) in NUMERIC.items():
        if q not in data:
            continue
        where = f"ODD '{source}': {q}"
        low, high = _bounds(data[q], q, where, unit, NUMERIC_RANGES[q], (0.0, math.inf))
        if low < 0 or high < 0:
            raise UserInputError(f"{where}: bounds must be >= 0 {unit}, got min {low:g}, max {high:g}")
        ranges[q] = Range(low, high)
    allowed: dict[str, tuple[str, ...]] = {}
    for q, (values, _) in CATEGORICAL.items():
        if q not in data:
            continue
        where = f"ODD '{source}': {q}"
        t = data[q]
        if not isinstance(t, Mapping) or set(t) != {"allowed"} or not isinstance(t["allowed"], list):
            raise UserInputError(f"{where} must be a table with one key, allowed = [...] of {', '.join(values)}")
        bad = [v for v in t["allowed"] if v not in values]
        if bad:
            raise UserInputError(f"{where}: unknown value(s) {bad}; allowed: {', '.join(values)}")
        if not t["allowed"]:
            raise UserInputError(f"{where}: allowed is empty: the domain is empty; allowed: {', '.join(values)}")
        allowed[q] = tuple(v for v in values if v in t["allowed"])
    glare = True
    if "sun_glare" in data:
        t = data["sun_glare"]
        if not isinstance(t, Mapping) or set(t) != {"allowed"} or not isinstance(t["allowed"], bool):
            raise UserInputError(f"ODD '{source}': sun_glare must be a table with allowed = true or false")
        glare = t["allowed"]
    odd = ODD(name=name, description=str(data.get("description", "")), ranges=ranges, allowed=allowed,
              sun_glare_allowed=glare, boundary_margin=margin, source=source,
              sun_altitude=_bounds(data[SUN_ALTITUDE], SUN_ALTITUDE, f"ODD '{source}': {SUN_ALTITUDE}", "deg",
                                   SUN_ALTITUDE_RANGE, (SUN_ALTITUDE_RANGE.low, SUN_ALTITUDE_RANGE.high))
              if SUN_ALTITUDE in data else None,
              traffic=parse_traffic_conditions(data["traffic"], f"ODD '{source}': traffic")
              if "traffic" in data else None)
    if model is not None and "visibility" in ranges:
        lo, hi = model.visibility_range_m
        r = ranges["visibility"]
        if r.low > hi or r.high < lo:
            raise UserInputError(f"ODD '{source}': visibility [{r.low:g}, {r.high:g}] m is out of reach of the "
                                 f"'{model.name}' backend, which shows {lo:.0f}..{hi:.0f} m")
    return odd


def load_odd(path: str | Path, model: ConditionsModel | None = None) -> ODD:
    """Read an ODD file; every error names the file and the field."""
    from genesis_rl.core.config import read_toml

    data = read_toml(path, "ODD", hint="; shipped ones: configs/odd/*.toml")
    if not data:  # an empty file would claim no domain at all: every weather inside it
        raise UserInputError(f"ODD '{path}' is empty; expected a name and at least one [quantity] table "
                             "(shipped ones: configs/odd/*.toml)")
    return parse_odd(data, str(path), model)


def check_start(odd: ODD, start: Weather, model: ConditionsModel) -> None:
    """The start weather must lie in the domain (glare aside: it depends on where the road points)."""
    bad = odd.violations(model.conditions(start, None), start)
    if bad:
        raise UserInputError(f"the start weather is outside the ODD '{odd.name}' ({odd.source}): "
                             f"{'; '.join(bad)}; choose env.start_weather inside it")
