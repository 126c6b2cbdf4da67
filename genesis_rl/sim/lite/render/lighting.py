"""Lighting of a weather: one pure function that the Panda3D light setup and the weather pass both read.

Both halves of the renderer must agree on where the sun is, how bright and what colour it is, what the
sky looks like and how far one can see; computing all of it here, from the knobs alone, keeps them in
step. Every quantity is a smooth function of the sun's altitude (smoothsteps and gaussians, no branches
on the value), so sweeping the sun from noon through sunset to night never makes the picture jump.

Conventions:

* world frame: x east, y north, z up;
* ``sun_azimuth_angle`` is measured counter-clockwise from +x (east) toward +y (north), so
  ``sun_direction = (cos alt cos az, cos alt sin az, sin alt)`` points FROM the scene TOWARD the sun;
* colours are 0..1 sRGB triples; ``sun_color`` and ``ambient_color`` are Panda3D light colours
  (colour * intensity), the rest are pixel colours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from genesis_rl.world.knobs import Weather
from genesis_rl.world.visibility import (  # noqa: F401  (names the renderer's callers read here)
    CLEAR_AIR_EXTINCTION,
    KOSCHMIEDER,
    extinctions,
    fog_density_for_visibility,
    fog_visibility_m,
)

Color = tuple[float, float, float]




@dataclass(frozen=True)
class Lighting:
    """Everything the renderer and the weather pass need to know about the light of one weather."""

    sun_direction: tuple[float, float, float]  # unit vector toward the sun (see module docstring)
    sun_color: Color  # directional light colour * intensity; 0 at night
    ambient_color: Color  # sky light; very dark blue at night, never pure black
    sky_zenith: Color  # sky colour straight up
    sky_horizon: Color  # sky colour at the horizon
    fog_color: Color  # airlight A of the Koschmieder law
    is_night: bool  # sun below ~-3 deg: vehicles switch their lights on
    headlight_strength: float  # 0 by day -> 1 at night, smooth through dusk
    shadow_darkness: float  # 0..1: how dark cast shadows are (0 at night / overcast)
    visibility_m: float  # meteorological visibility of fog + rain + haze (Koschmieder, fog_distance ignored)
    fog_extinction: float = CLEAR_AIR_EXTINCTION  # beta of fog + clear-air haze (1/m), beyond fog_distance
    rain_extinction: float = 0.0  # beta of falling rain, 1/m; acts from the camera on
    cloud_cover: float = 0.0  # 0..1 effective cover (cloudiness, raised by rain): hides the sun


def smoothstep(edge0: float, edge1: float, x: float) -> float:
    """C1-continuous ramp from 0 (x <= edge0) to 1 (x >= edge1)."""
    t = min(1.0, max(0.0, (x - edge0) / (edge1 - edge0)))
    return t * t * (3.0 - 2.0 * t)


def _lerp(a: Color, b: Color, t: float) -> Color:
    return (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t)


def _scale(a: Color, s: float) -> Color:
    return (a[0] * s, a[1] * s, a[2] * s)


def luminance(c: Color) -> float:
    """Rec. 709 luma of an sRGB triple (good enough for mixing weights)."""
    return 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]


def _desaturate(c: Color, t: float, tint: Color = (1.0, 1.0, 1.0)) -> Color:
    y = luminance(c)
    return _lerp(c, (y * tint[0], y * tint[1], y * tint[2]), t)


def _clip01(c: Color) -> Color:
    return (min(1.0, max(0.0, c[0])), min(1.0, max(0.0, c[1])), min(1.0, max(0.0, c[2])))


# Reference colours (sRGB 0..1).
_ZENITH_DAY: Color = (0.20, 0.42, 0.80)
_HORIZON_DAY: Color = (0.66, 0.79, 0.93)
_ZENITH_SUNSET: Color = (0.26, 0.27, 0.50)
_HORIZON_SUNSET: Color = (0.98, 0.56, 0.28)
_ZENITH_NIGHT: Color = (0.006, 0.010, 0.030)
_HORIZON_NIGHT: Color = (0.025, 0.032, 0.060)
_OVERCAST: Color = (0.70, 0.72, 0.75)
_SUN_NOON: Color = (1.0, 0.97, 0.92)
_SUN_SUNSET: Color = (1.0, 0.50, 0.22)
_AMBIENT_DAY: Color = (0.36, 0.40, 0.48)
_AMBIENT_NIGHT: Color = (0.030, 0.036, 0.052)


def lighting_for(weather: Weather) -> Lighting:
    """The lighting of ``weather``: a pure, continuous function of the knobs."""
    alt = float(weather["sun_altitude_angle"])
    az = float(weather["sun_azimuth_angle"])
    cloud = float(weather["cloudiness"]) / 100.0
    rain = float(weather["precipitation"]) / 100.0
    fog = float(weather["fog_density"])

    ra, rz = math.radians(alt), math.radians(az)
    sun_direction = (math.cos(ra) * math.cos(rz), math.cos(ra) * math.sin(rz), math.sin(ra))

    # Rain comes from clouds: it raises the effective cover, which hides the sun and greys the sky.
    cover = 1.0 - (1.0 - cloud) * (1.0 - 0.9 * rain)

    # Direct sun: fades in as the disk clears the horizon, reddens and dims through more air mass.
    sun_up = smoothstep(-3.0, 8.0, alt)
    air_mass_gain = 0.45 + 0.55 * smoothstep(0.0, 45.0, alt)
    warmth = 1.0 - smoothstep(2.0, 35.0, alt)
    direct = 0.9 * sun_up * air_mass_gain * (1.0 - 0.92 * cover)
    sun_rgb = _desaturate(_lerp(_SUN_NOON, _SUN_SUNSET, warmth), 0.7 * cover)
    sun_color = _scale(sun_rgb, direct)

    # Sky light: from full day (sun 20 deg up) down to night at the end of nautical twilight (-14 deg).
    day_amb = smoothstep(-14.0, 20.0, alt)
    amb_day = _lerp(_AMBIENT_DAY, (0.34, 0.30, 0.36), 0.5 * warmth)  # dusk light is warmer, purplish
    amb_day = _desaturate(_scale(amb_day, 1.0 - 0.30 * cover), 0.6 * cover)
    ambient_color = _lerp(_AMBIENT_NIGHT, amb_day, day_amb)

    # Sky: day and night blended by altitude, a sunset band around the horizon crossing, then grey clouds.
    day_w = smoothstep(-8.0, 15.0, alt)
    set_w = 0.85 * math.exp(-(((alt - 1.0) / 11.0) ** 2))
    set_bright = 0.25 + 0.75 * smoothstep(-11.0, 4.0, alt)
    zenith = _lerp(_ZENITH_NIGHT, _ZENITH_DAY, day_w)
    horizon = _lerp(_HORIZON_NIGHT, _HORIZON_DAY, day_w)
    zenith = _lerp(zenith, _scale(_ZENITH_SUNSET, set_bright), set_w * 0.8)
    horizon = _lerp(horizon, _scale(_HORIZON_SUNSET, set_bright), set_w)
    sky_light = 0.03 + 0.97 * smoothstep(-10.0, 12.0, alt)  # brightness of a grey overcast sky
    grey = _scale(_OVERCAST, sky_light * (1.0 - 0.35 * rain))
    grey_zenith = _scale(grey, 0.92)
    zenith = _lerp(zenith, grey_zenith, 0.95 * cover)
    horizon = _lerp(horizon, grey, 0.95 * cover)

    # Airlight: the horizon colour, mostly desaturated (fog scatters every wavelength alike).
    fog_color = _lerp(_desaturate(horizon, 1.0, (0.98, 1.0, 1.03)), horizon, 0.35)

    fog_extinction, rain_extinction = extinctions(fog, weather["precipitation"])
    visibility_m = KOSCHMIEDER / (fog_extinction + rain_extinction)

    headlight_strength = 1.0 - smoothstep(-6.0, 6.0, alt)
    shadow_darkness = 0.8 * sun_up * (1.0 - cover) ** 1.2

    return Lighting(
        sun_direction=sun_direction,
        sun_color=_clip01(sun_color),
        ambient_color=_clip01(ambient_color),
        sky_zenith=_clip01(zenith),
        sky_horizon=_clip01(horizon),
        fog_color=_clip01(fog_color),
        is_night=alt < -3.0,
        headlight_strength=headlight_strength,
        shadow_darkness=shadow_darkness,
        visibility_m=visibility_m,
        fog_extinction=fog_extinction,
        rain_extinction=rain_extinction,
        cloud_cover=cover,
    )
