"""Our weather knobs <-> OpenSCENARIO's ``Environment``, both ways, per version (docs/openscenario.md).

The forward map writes what each knob means in the standard's physical terms where the standard has a term,
following CARLA ScenarioRunner's reader where it departs from the standard (sun ``intensity`` as the share of
sunlight the clouds let through, not lux), since ScenarioRunner is the tool that runs these files in CARLA.
Every quantity it writes is invertible, so :func:`knobs_from_environment` gives back the knobs exactly for the
knobs listed in :func:`expressed_knobs`; the others (wetness, wind before 1.2, fog_distance, CARLA's
scattering and dust) have no place in the standard and travel in our ``CustomCommandAction`` only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from genesis_rl.world.odd.conditions import precipitation_for_rain_rate, rain_rate_mm_h
from genesis_rl.world.visibility import fog_density_for_visibility, fog_visibility_m

#: OpenSCENARIO 1.x minor versions we write: 0 (what ScenarioRunner reads) to 3
MINOR_VERSIONS = (0, 1, 2, 3)
#: road friction at precipitation_deposits 100 % as a share of dry (wet asphalt keeps about 0.5-0.7 of its
#: dry friction); ours, linear in the deposits, so that the deposits travel as ``frictionScaleFactor``
WET_FRICTION_SCALE = 0.6
#: wind speed at wind_intensity 100 % [m/s] (ours: CARLA's wind knob has no unit; 20 m/s is a gale, Beaufort 8)
FULL_WIND_M_S = 20.0
#: the date written into ``TimeOfDay`` (animation off: the sun is set by ``Sun``, as ScenarioRunner does)
DATE = (2026, 6, 21)


def expressed_knobs(minor: int) -> tuple[str, ...]:
    """The knobs the standard's Environment carries exactly in version 1.``minor``."""
    base = ("sun_altitude_angle", "sun_azimuth_angle", "cloudiness", "fog_density", "precipitation",
            "precipitation_deposits")
    return base + (("wind_intensity",) if minor >= 2 else ())


@dataclass(frozen=True)
class OscEnvironment:
    """One Environment in the standard's terms (angles in radians, as OpenSCENARIO writes them)."""

    sun_intensity: float  # share of sunlight through the clouds, 0..1 (ScenarioRunner: cloudiness = 100 - 100 x)
    sun_azimuth: float  # [rad], CARLA's sun_azimuth_angle in radians (ScenarioRunner's reading)
    sun_elevation: float  # [rad]
    cloud_state: str  # 1.0/1.1 CloudState (free, cloudy, overcast, rainy) or 1.2+ FractionalCloudCover (oktas)
    fog_visual_range: float  # [m], the visibility of lite's fog alone (Koschmieder)
    precipitation_type: str  # dry or rain
    precipitation_intensity: float  # 1.0: 0..1 (ScenarioRunner: precipitation = 100 x); 1.1+: rain rate [mm/h]
    friction_scale_factor: float  # 1 dry .. WET_FRICTION_SCALE at deposits 100 %
    wetness: str | None  # 1.2+: dry, moist, wetWithPuddles, lowFlooded, highFlooded
    wind_speed: float | None  # 1.2+: [m/s]
    hour: int  # TimeOfDay: a clock time matching the sun's elevation (informative, animation off)


def _cloud_state(cloudiness: float, precipitation: float, minor: int) -> str:
    if minor >= 2:
        oktas = min(8, max(0, round(cloudiness / 12.5)))
        return ("zeroOktas", "oneOktas", "twoOktas", "threeOktas", "fourOktas", "fiveOktas", "sixOktas",
                "sevenOktas", "eightOktas")[oktas]
    if precipitation > 0.0:
        return "rainy"
    return "free" if cloudiness < 25.0 else "cloudy" if cloudiness < 75.0 else "overcast"


def _wetness(deposits: float, wetness: float) -> str:
    level = max(deposits, wetness)
    if deposits >= 90.0:
        return "lowFlooded"
    if deposits >= 60.0:
        return "wetWithPuddles"
    return "moist" if level >= 5.0 else "dry"


def environment_of(knobs: Mapping[str, float], minor: int = 0) -> OscEnvironment:
    """The Environment of one step's knobs in version 1.``minor``."""
    if minor not in MINOR_VERSIONS:
        raise ValueError(f"OpenSCENARIO 1.{minor}: allowed minor versions {MINOR_VERSIONS}")
    rain = float(knobs["precipitation"])
    elevation = math.radians(float(knobs["sun_altitude_angle"]))
    return OscEnvironment(
        sun_intensity=1.0 - float(knobs["cloudiness"]) / 100.0,
        sun_azimuth=math.radians(float(knobs["sun_azimuth_angle"])),
        sun_elevation=elevation,
        cloud_state=_cloud_state(float(knobs["cloudiness"]), rain, minor),
        fog_visual_range=fog_visibility_m(float(knobs["fog_density"])),
        precipitation_type="rain" if rain > 0.0 else "dry",
        precipitation_intensity=rain / 100.0 if minor == 0 else rain_rate_mm_h(rain),
        friction_scale_factor=1.0 - (1.0 - WET_FRICTION_SCALE) * float(knobs["precipitation_deposits"]) / 100.0,
        wetness=_wetness(float(knobs["precipitation_deposits"]), float(knobs["wetness"])) if minor >= 2 else None,
        wind_speed=FULL_WIND_M_S * float(knobs["wind_intensity"]) / 100.0 if minor >= 2 else None,
        hour=12 if elevation > math.radians(45) else 8 if elevation > 0 else 21,
    )


def knobs_from_environment(env: OscEnvironment, minor: int = 0) -> dict[str, float]:
    """The knobs an Environment carries (``expressed_knobs(minor)``), inverted exactly from what
    :func:`environment_of` wrote; values are clamped to the knobs' ranges (a file edited by hand may exceed
    them)."""
    def clamp(v: float, lo: float, hi: float) -> float:
        return min(hi, max(lo, v))

    rain = env.precipitation_intensity if env.precipitation_type == "rain" else 0.0
    out = {
        "sun_altitude_angle": clamp(math.degrees(env.sun_elevation), -90.0, 90.0),
        "sun_azimuth_angle": math.degrees(env.sun_azimuth) % 360.0,
        "cloudiness": clamp(100.0 * (1.0 - env.sun_intensity), 0.0, 100.0),
        "fog_density": fog_density_for_visibility(env.fog_visual_range),
        "precipitation": clamp(100.0 * rain if minor == 0 else precipitation_for_rain_rate(rain), 0.0, 100.0),
        "precipitation_deposits": clamp(100.0 * (1.0 - env.friction_scale_factor) / (1.0 - WET_FRICTION_SCALE),
                                        0.0, 100.0),
    }
    if minor >= 2 and env.wind_speed is not None:
        out["wind_intensity"] = clamp(100.0 * env.wind_speed / FULL_WIND_M_S, 0.0, 100.0)
    return out
