"""Scripted schedules for the timing members' ground truth: what a one-knob sweep cannot show, the order of two
events (docs/zoo.md, `fog_braking`). Used by ``scripts/fog_braking_onsets.py`` and ``tests/test_zoo_sweep.py``."""

from __future__ import annotations

from collections.abc import Callable

from genesis_rl.world.knobs import Weather, parse_weather
from genesis_rl.world.odd.dynamics import natural_rate

#: fog_density for (about) 50 m of visibility on lite, the floor of highway_fog_braking (56.8 exactly)
FOG_AT_50_M = 57.0
#: precipitation at 7.6 mm/h, the domain's most
RAIN_MODERATE = 50.0
#: the lead's braking demand the schedules ramp to, the domain's most [m/s^2]
LEAD_DECEL = 6.0


def fog_then_brake(start: str, onset_s: float, dt: float, *, held: bool = False,
                   rain: bool = False) -> Callable[[int], Weather]:
    """The weather at each step: from ``start`` (``EnvConfig.start_weather`` text) the fog thickens at its natural
    rate toward 50 m of visibility from the first step (``held``: it is there from the first step), rain sets in at
    its natural rate beside it when ``rain``, and the lead's braking demand rises at its natural rate to
    :data:`LEAD_DECEL` from ``onset_s``."""
    base = parse_weather(start)
    fog0 = FOG_AT_50_M if held else base.values["fog_density"]
    fog_rate, rain_rate, brake_rate = (natural_rate(k) for k in ("fog_density", "precipitation", "lead_decel"))

    def weather(step: int) -> Weather:
        t = step * dt
        return base.replace(fog_density=min(FOG_AT_50_M, fog0 + fog_rate * t),
                            precipitation=min(RAIN_MODERATE, rain_rate * t) if rain else base.values["precipitation"],
                            lead_decel=min(LEAD_DECEL, max(0.0, brake_rate * (t - onset_s))))
    return weather
