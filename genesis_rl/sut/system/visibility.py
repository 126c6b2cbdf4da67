"""Meteorological visibility from one camera frame and its depth, as an onboard fog estimator would see it.

Koschmieder's law: an object of luminance ``L0`` at distance ``d`` seen through air of extinction ``beta``
appears as ``L = L0 t + A (1 - t)``, ``t = exp(-beta d)``, where ``A`` is the airlight (the horizon sky's
luminance in fog). The road is one surface of about constant ``L0`` seen at every distance, so
``log |A - L(d)|`` falls linearly in ``d`` with slope ``-beta``; visibility is ``3.912 / beta`` (2 % contrast).
This is the road-luminance-profile idea of Hautière et al. (2006, "Automatic fog detection and estimation of
visibility distance through use of an onboard camera"), with the depth that our system already reads for its
localisation in place of their flat-road geometry. It reads 60-80 % of the true visibility on lite's highway
(a conservative bias: the road's far bins sit closer to the airlight than Koschmieder's law alone gives),
monotonic in it; docs/zoo.md gives the calibration.
"""

from __future__ import annotations

import numpy as np

#: visibility = KOSCHMIEDER / extinction, for a 2 % contrast threshold
KOSCHMIEDER = 3.912
#: the depth bins of the road profile [m]
BIN_EDGES = np.arange(5.0, 90.0, 5.0)
#: a bin whose luminance is within this of the airlight is lost in the noise; the profile stops there [0-255]
NOISE_FLOOR = 3.0
#: what the estimator reports when the air is clear beyond what the road profile can tell [m]
CLEAR_AIR_M = 2000.0


def estimate_visibility(rgb: np.ndarray, depth: np.ndarray, max_range: float) -> float | None:
    """Visibility [m] in ``(0, CLEAR_AIR_M]``, or None when the frame shows too little sky or road to tell."""
    lum = rgb.astype(np.float32).mean(axis=2)
    h, w = lum.shape
    sky = depth >= 0.99 * max_range
    upper = sky[: h // 2]
    if upper.sum() < 20:
        return None
    airlight = float(np.median(lum[: h // 2][upper]))
    ground = np.zeros_like(sky)
    ground[h // 2 :, w // 4 : 3 * w // 4] = True  # the road ahead, below the horizon
    ground &= ~sky
    d, lum_ground = depth[ground], lum[ground]
    centres, log_dev = [], []
    for lo, hi in zip(BIN_EDGES[:-1], BIN_EDGES[1:], strict=True):
        in_bin = (d >= lo) & (d < hi)
        if in_bin.sum() < 10:
            continue
        dev = abs(airlight - float(np.median(lum_ground[in_bin])))
        if dev < NOISE_FLOOR:
            break
        centres.append(0.5 * (lo + hi))
        log_dev.append(np.log(dev))
    if len(centres) < 3:
        return None
    beta = -float(np.polyfit(centres, log_dev, 1)[0])
    return KOSCHMIEDER / beta if beta > KOSCHMIEDER / CLEAR_AIR_M else CLEAR_AIR_M
