"""Knobs <-> ``carla.WeatherParameters``: every field by name, and CARLA's named presets.

Each knob declares the ``carla.WeatherParameters`` field it sets (``KnobSpec.carla_field``; the built-in knobs
bear CARLA's field names), and a knob with none (a user's lite-only knob) is left out. What this module adds
is the check that the two sets agree (a CARLA release that adds or renames a field fails loudly, not
silently), the float32 round-off of the wire format, and CARLA's sentinels (-1 in
``WeatherParameters.Default`` means "keep the map's value") which have no place in a knob range.
"""

from __future__ import annotations

import math
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.carla._carla import require_carla
from genesis_rl.world.knobs import KNOBS, KnobSpec, Weather

#: decimals kept when reading CARLA's float32 fields back (0.0331 comes back as 0.033100001)
_DECIMALS = 4


def carla_weather_fields() -> tuple[str, ...]:
    """The data fields of ``carla.WeatherParameters`` in this client (lower-case properties; the
    capitalised attributes are presets)."""
    carla = require_carla()
    cls = carla.WeatherParameters
    return tuple(sorted(n for n in dir(cls) if not n.startswith("_") and n.islower()
                        and isinstance(getattr(cls, n), property)))


def carla_preset_names() -> tuple[str, ...]:
    """CARLA's named weathers (ClearNoon, HardRainNight, ...), without ``Default`` (map-dependent)."""
    carla = require_carla()
    cls = carla.WeatherParameters
    return tuple(sorted(n for n in dir(cls) if n[:1].isupper() and n != "Default"
                        and isinstance(getattr(cls, n), cls)))


def carla_knobs() -> dict[str, KnobSpec]:
    """The knobs CARLA realises, by the ``carla.WeatherParameters`` field each sets."""
    return {k.carla_field: k for k in KNOBS.values() if k.carla_field}


def check_fields() -> None:
    """Fail when the client's WeatherParameters and the knob specs disagree on names."""
    fields, knobs = set(carla_weather_fields()), set(carla_knobs())
    if fields != knobs:
        raise RuntimeError(
            "carla.WeatherParameters fields and genesis_rl knobs disagree: "
            f"only in CARLA {sorted(fields - knobs)}, "
            f"only in knobs {sorted(knobs - fields)}; this backend is written for carla 0.9.16"
        )


def to_carla(weather: Weather) -> Any:
    """A ``carla.WeatherParameters`` with every field set from the knob that declares it."""
    carla = require_carla()
    check_fields()
    params = carla.WeatherParameters()
    for field, spec in carla_knobs().items():
        setattr(params, field, float(weather[spec.name]))
    return params


def from_carla(params: Any) -> Weather:
    """Knob values read from a ``carla.WeatherParameters`` (e.g. ``world.get_weather()``).

    Values outside a knob's range (CARLA accepts them, and uses -1 as "unset") are clipped; angles that
    wrap (sun azimuth) are wrapped, so a preset's azimuth of -1 reads as 359."""
    check_fields()
    values: dict[str, float] = {}
    for field, spec in carla_knobs().items():
        v = float(getattr(params, field))
        if not math.isfinite(v):
            raise UserInputError(f"carla weather field '{field}' is not finite: {v}")
        values[spec.name] = round(spec.fit(v), _DECIMALS)
    return Weather.from_recorded(values)  # knobs CARLA lacks stay at their defaults


def carla_preset(name: str) -> Weather:
    """One of CARLA's presets (``HardRainNight`` ...) as knob values."""
    carla = require_carla()
    names = carla_preset_names()
    if name not in names:
        raise UserInputError(f"unknown CARLA weather preset '{name}'; allowed: {', '.join(names)}")
    return from_carla(getattr(carla.WeatherParameters, name))


def carla_presets() -> dict[str, Weather]:
    """Every CARLA preset as knob values, keyed by CARLA's name."""
    return {name: carla_preset(name) for name in carla_preset_names()}


def same_weather(a: Any, b: Any, tol: float = 1e-3) -> bool:
    """Two ``carla.WeatherParameters`` equal field by field within ``tol`` (float32 on the wire)."""
    return all(abs(float(getattr(a, n)) - float(getattr(b, n))) <= tol for n in carla_weather_fields())
