"""How far one can see in a weather: the fog and rain extinction that the renderer draws and the ODD reads.

Kept below the simulator so that the operational domain and the renderer share one definition without the
domain asking the renderer (the lite renderer imports these; ``world.odd.conditions`` reads them).
"""

from __future__ import annotations

import math

#: Koschmieder's constant: visibility V = 3.912 / beta for a 2% contrast threshold.
KOSCHMIEDER = 3.912

#: fog_density -> meteorological visibility (m); log-interpolated between the points.
_FOG_VISIBILITY_TABLE: tuple[tuple[float, float], ...] = (
    (0.0, 3000.0),
    (10.0, 400.0),
    (30.0, 120.0),
    (60.0, 45.0),
    (90.0, 18.0),
    (100.0, 12.0),
)
#: extinction of clear air (haze) per metre: what fog_density 0 gives.
CLEAR_AIR_EXTINCTION = KOSCHMIEDER / _FOG_VISIBILITY_TABLE[0][1]
#: precipitation 100 alone gives a visibility of about 150 m.
_RAIN_EXTINCTION_MAX = KOSCHMIEDER / 150.0 - CLEAR_AIR_EXTINCTION


def fog_visibility_m(fog_density: float) -> float:
    """Visibility (m) of fog alone, log-interpolated through the calibration table."""
    d = min(100.0, max(0.0, fog_density))
    for (d0, v0), (d1, v1) in zip(_FOG_VISIBILITY_TABLE, _FOG_VISIBILITY_TABLE[1:], strict=False):
        if d <= d1:
            t = (d - d0) / (d1 - d0)
            return math.exp(math.log(v0) + (math.log(v1) - math.log(v0)) * t)
    return _FOG_VISIBILITY_TABLE[-1][1]


def fog_density_for_visibility(visibility_m: float) -> float:
    """The fog_density whose fog alone gives ``visibility_m`` (the inverse of :func:`fog_visibility_m`, clamped
    to the table: 3000 m and more is density 0, 12 m and less is 100)."""
    table = _FOG_VISIBILITY_TABLE
    v = min(table[0][1], max(table[-1][1], float(visibility_m)))
    for (d0, v0), (d1, v1) in zip(table, table[1:], strict=False):
        if v >= v1:
            t = (math.log(v) - math.log(v0)) / (math.log(v1) - math.log(v0))
            return d0 + (d1 - d0) * t
    return table[-1][0]


def extinctions(fog_density: float, precipitation: float) -> tuple[float, float]:
    """beta of fog + clear-air haze and beta of falling rain [1/m] (visibility = KOSCHMIEDER / their sum)."""
    rain = float(precipitation) / 100.0
    return KOSCHMIEDER / fog_visibility_m(float(fog_density)), _RAIN_EXTINCTION_MAX * rain**1.2
