"""The visibility-adaptive system (issue 33's competent controller, the fog_braking member): its camera's
visibility estimate, the speed it allows for a sight distance, its smoothing, and its settings' checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.system.adaptive import speed_for_sight
from genesis_rl.sut.system.protocol import load_system
from genesis_rl.sut.system.visibility import CLEAR_AIR_M, KOSCHMIEDER, estimate_visibility


def _foggy_frame(visibility_m: float, road: float = 60.0, airlight: float = 200.0) -> tuple[np.ndarray, np.ndarray]:
    """A 120 x 160 frame of a flat road under a sky, fogged by Koschmieder's law: the road's depth grows
    toward the horizon (the middle row), the sky is at the camera's range."""
    h, w, max_range = 120, 160, 200.0
    rows = np.arange(h, dtype=np.float64)[:, None].repeat(w, axis=1)
    depth = np.where(rows > h // 2, 240.0 / np.maximum(rows - h // 2, 1e-6), max_range)  # 4 m at the bottom row
    depth = np.minimum(depth, max_range)
    t = np.exp(-KOSCHMIEDER / visibility_m * depth)
    lum = np.where(depth >= max_range, airlight, road * t + airlight * (1 - t))
    return np.repeat(lum[:, :, None], 3, axis=2).astype(np.uint8), depth.astype(np.float32)


@pytest.mark.parametrize("visibility", [40.0, 80.0, 150.0])
def test_the_road_profile_recovers_koschmieder_visibility(visibility) -> None:
    rgb, depth = _foggy_frame(visibility)
    assert estimate_visibility(rgb, depth, 200.0) == pytest.approx(visibility, rel=0.15)


def test_clear_air_and_frames_without_sky_or_road() -> None:
    rgb, depth = _foggy_frame(1e6)
    assert estimate_visibility(rgb, depth, 200.0) == CLEAR_AIR_M  # the road keeps its contrast: clear
    no_sky = depth.copy()
    no_sky[no_sky >= 200.0] = 150.0
    assert estimate_visibility(rgb, no_sky, 200.0) is None  # no airlight to measure against
    assert estimate_visibility(rgb, np.full_like(depth, 200.0), 200.0) is None  # all sky: no road


def test_speed_for_sight_stops_within_it() -> None:
    for sight in (5.0, 17.0, 60.0):
        v = speed_for_sight(sight, 0.5, 5.0)
        assert v * 0.5 + v * v / (2 * 5.0) == pytest.approx(sight)
    assert speed_for_sight(0.0, 0.5, 5.0) == 0.0


def test_the_estimate_follows_the_fog_over_its_smoothing() -> None:
    """After a jump from 150 m to 50 m of visibility, a 12 s smoothing still reads more than 100 m two seconds
    later, where 0.5 s reads within 10 % of 50 m; the speed cap follows the estimate."""
    from genesis_rl.sut.system.adaptive import AdaptiveSystem

    class _Context:
        dt = 0.05

        class camera:  # noqa: N801
            max_range = 200.0

    readings = {}
    for smoothing in (12.0, 0.5):
        system = AdaptiveSystem(smoothing_s=smoothing)
        system.context = _Context()  # type: ignore[assignment]  # all the estimate reads of an episode
        system._update_visibility(_frame_obj(150.0))
        for _ in range(40):  # two seconds at 20 Hz
            system._update_visibility(_frame_obj(50.0))
        readings[smoothing] = system.visibility_m
    assert readings[12.0] > 100.0
    assert readings[0.5] == pytest.approx(50.0, rel=0.1)
    assert math.isfinite(speed_for_sight(0.3 * readings[12.0], 0.5, 5.0))


def _frame_obj(visibility: float):  # noqa: ANN202
    from genesis_rl.sim.interface import SensorFrame

    rgb, depth = _foggy_frame(visibility)
    return SensorFrame(0, rgb, depth, [])


@pytest.mark.parametrize(("kwargs", "field"), [({"smoothing_s": -1.0}, "smoothing_s"),
                                               ({"sight_fraction": 0.0}, "sight_fraction"),
                                               ({"decel": 50.0}, "decel")])
def test_bad_settings_name_the_field(kwargs, field) -> None:
    with pytest.raises(UserInputError, match=field):
        load_system("adaptive", **kwargs)
