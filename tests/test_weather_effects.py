"""The weather pass and the lighting model, on synthetic frames (no Panda3D needed).

Each knob must change the picture the way it does outdoors; these tests pin the direction and the rough
size of every effect with numbers, so that a regression that, say, makes fog brighten far cars shows.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from genesis_rl.sim.lite.render import labels as L
from genesis_rl.sim.lite.render import weather_effects
from genesis_rl.sim.lite.render.lighting import lighting_for
from genesis_rl.sim.lite.render.weather_effects import WeatherCompositor, exposure_gain, tone_curve
from genesis_rl.world.knobs import Weather

W, H, FOV = 160, 120, 90.0
NEAR = (slice(62, 80), slice(30, 60))  # vehicle at 10 m
FAR = (slice(64, 70), slice(100, 110))  # vehicle at 60 m
FAR_BG = (slice(52, 58), slice(100, 110))  # building at 80 m just above the far vehicle
NEAR_BG = (slice(52, 58), slice(30, 60))


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sky on top, a building band at 80 m, road below the horizon, a dark car at 10 m and one at 60 m."""
    rgb = np.zeros((H, W, 3), np.uint8)
    depth = np.full((H, W), 1000.0, np.float32)
    lab = np.zeros((H, W), np.uint8)
    rgb[40:60] = (150, 130, 120)
    depth[40:60] = 80.0
    lab[40:60] = L.BUILDING
    rows = np.arange(60, H, dtype=np.float32) + 0.5 - H / 2
    focal = (W / 2) / math.tan(math.radians(FOV) / 2)
    rgb[60:] = (110, 110, 112)
    depth[60:] = np.minimum(1.5 * focal / rows, 80.0)[:, None]
    lab[60:] = L.ROAD
    rgb[:, :12][60:] = (90, 140, 60)
    lab[:, :12][60:] = L.GROUND
    for (ys, xs), d, label in ((NEAR, 10.0, 32), (FAR, 60.0, 33)):
        rgb[ys, xs] = (25, 25, 28)
        depth[ys, xs] = d
        lab[ys, xs] = label
    return rgb, depth, lab


def _render(weather: Weather, yaw: float = 0.0, step: int = 0, seed: int = 7) -> np.ndarray:
    rgb, depth, lab = _scene()
    comp = WeatherCompositor(W, H, FOV, seed)
    return comp.apply(rgb, depth, lab, weather, lighting_for(weather), yaw, 0.0, step).astype(np.float64)


def _lum(img: np.ndarray) -> np.ndarray:
    return img @ np.array([0.2126, 0.7152, 0.0722])


def _contrast(img: np.ndarray, obj: tuple[slice, slice], bg: tuple[slice, slice]) -> float:
    return abs(float(_lum(img[obj]).mean() - _lum(img[bg]).mean()))


NOON = {"sun_altitude_angle": 60.0, "sun_azimuth_angle": 180.0, "cloudiness": 0.0}


def test_inputs_untouched_and_output_shape() -> None:
    rgb, depth, lab = _scene()
    copies = rgb.copy(), depth.copy(), lab.copy()
    wx = Weather.from_partial({"fog_density": 40, "precipitation": 60, "precipitation_deposits": 60})
    out = WeatherCompositor(W, H, FOV, 1).apply(rgb, depth, lab, wx, lighting_for(wx), 0.3, 0.05, 3)
    assert out.shape == (H, W, 3) and out.dtype == np.uint8
    for a, b in zip((rgb, depth, lab), copies, strict=True):
        np.testing.assert_array_equal(a, b)


def test_fog_hides_far_vehicles_more_than_near_ones() -> None:
    clear = _render(Weather.from_partial(NOON))
    fog = _render(Weather.from_partial({**NOON, "fog_density": 60}))
    far_ratio = _contrast(fog, FAR, FAR_BG) / _contrast(clear, FAR, FAR_BG)
    near_ratio = _contrast(fog, NEAR, NEAR_BG) / _contrast(clear, NEAR, NEAR_BG)
    assert far_ratio < 0.5
    assert near_ratio > far_ratio + 0.2
    # the far car fades toward the (bright) airlight, it does not turn black
    assert _lum(fog[FAR]).mean() > _lum(clear[FAR]).mean() + 40


def test_fog_distance_keeps_fog_away() -> None:
    wx = Weather.from_partial({**NOON, "fog_density": 60})
    far_fog = _render(wx.replace(fog_distance=70.0))
    near_fog = _render(wx)
    assert _contrast(far_fog, FAR, FAR_BG) > 2 * _contrast(near_fog, FAR, FAR_BG)


def test_night_is_dark() -> None:
    day, night = lighting_for(Weather.from_partial(NOON)), lighting_for(Weather.from_partial(
        {"sun_altitude_angle": -40.0}))
    assert sum(night.ambient_color) * 5 < sum(day.ambient_color)
    assert sum(night.sun_color) == 0.0 and sum(day.sun_color) > 1.0
    assert night.is_night and not day.is_night
    assert night.headlight_strength == 1.0 and day.headlight_strength == 0.0
    assert 0.01 < min(night.ambient_color) and max(night.ambient_color) < 0.08  # dark, not black
    sky = _scene()[2] == L.SKY
    day_img = _render(Weather.from_partial(NOON))
    night_img = _render(Weather.from_partial({"sun_altitude_angle": -40.0}))
    assert _lum(night_img[sky]).mean() * 5 < _lum(day_img[sky]).mean()


def test_wet_road_darkens_only_the_road() -> None:
    dry = _render(Weather.from_partial(NOON))
    wet = _render(Weather.from_partial({**NOON, "precipitation_deposits": 90.0}))
    lab = _scene()[2]
    road = np.zeros_like(lab, bool)
    road[90:, 20:] = True  # well inside the road, away from reflections of the near car
    assert (lab[road] == L.ROAD).all()
    assert _lum(wet[road]).mean() < 0.8 * _lum(dry[road]).mean()
    # other labels: same seed and step -> same noise, so they match closely (blur seams excluded)
    regions = ((slice(5, 35), slice(None)), (slice(42, 58), slice(65, 95)), (slice(63, 79), slice(33, 57)))
    for region in regions:
        assert np.abs(wet[region] - dry[region]).mean() < 1.5


def test_puddles_mirror_when_deep(monkeypatch: pytest.MonkeyPatch) -> None:
    # the puddle is compared with road farther from the centre: without vignetting, which darkens that
    monkeypatch.setattr(weather_effects, "VIGNETTE", 0.0)
    rgb, depth, lab = _scene()
    lab[95:110, 80:120] = L.PUDDLE
    comp = WeatherCompositor(W, H, FOV, 3)

    def puddle(deposits: float) -> float:
        wx = Weather.from_partial({**NOON, "precipitation_deposits": deposits})
        out = comp.apply(rgb, depth, lab, wx, lighting_for(wx), 0.0, 0.0, 0).astype(np.float64)
        return float(_lum(out[97:108, 85:115]).mean() - _lum(out[97:108, 125:150]).mean())

    # shallow: a puddle looks like the road; deep: it mirrors the bright building/sky above the horizon
    assert abs(puddle(10.0)) < 3.0
    assert puddle(100.0) > 15.0


def test_rain_lowers_visibility() -> None:
    clear = _render(Weather.from_partial(NOON))
    rain = _render(Weather.from_partial({**NOON, "precipitation": 90.0}))
    assert _contrast(rain, FAR, FAR_BG) < 0.6 * _contrast(clear, FAR, FAR_BG)
    assert _contrast(rain, NEAR, NEAR_BG) < _contrast(clear, NEAR, NEAR_BG)


def test_low_sun_ahead_glares() -> None:
    low = {"sun_altitude_angle": 5.0, "cloudiness": 0.0}
    ahead = _render(Weather.from_partial({**low, "sun_azimuth_angle": 0.0}), yaw=0.0)
    behind = _render(Weather.from_partial({**low, "sun_azimuth_angle": 180.0}), yaw=0.0)
    assert _lum(ahead).mean() > _lum(behind).mean() + 10
    # the veiling glare also washes out the near car against the road/building
    assert _contrast(ahead, NEAR, NEAR_BG) < _contrast(behind, NEAR, NEAR_BG)


def test_deterministic_in_seed_and_step() -> None:
    wx = Weather.from_partial({**NOON, "precipitation": 70.0, "fog_density": 20.0})
    a, b, c = _render(wx, step=5), _render(wx, step=5), _render(wx, step=6)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).mean() > 0.5
    assert np.abs(_render(wx, step=5, seed=8) - a).mean() > 0.5


def test_lighting_is_continuous_in_sun_altitude() -> None:
    base = Weather.from_partial({"cloudiness": 20.0})
    prev = None
    for alt in np.arange(-90.0, 90.0001, 0.5):
        lt = lighting_for(base.replace(sun_altitude_angle=float(alt)))
        colours = np.array([*lt.sun_color, *lt.ambient_color, *lt.sky_zenith, *lt.sky_horizon, *lt.fog_color])
        ramps = np.array([lt.headlight_strength, lt.shadow_darkness])
        assert np.all((colours >= 0.0) & (colours <= 1.0)) and np.all((ramps >= 0.0) & (ramps <= 1.0))
        if prev is not None:
            assert np.abs(colours - prev[0]).max() < 0.04, f"colour jump at {alt} deg"
            assert np.abs(ramps - prev[1]).max() < 0.07, f"headlight/shadow jump at {alt} deg"
        prev = (colours, ramps)


@pytest.mark.parametrize(
    ("fog", "low", "high"),
    [(0.0, 2000.0, 4000.0), (30.0, 90.0, 150.0), (60.0, 35.0, 55.0), (90.0, 14.0, 22.0)],
)
def test_fog_visibility_calibration(fog: float, low: float, high: float) -> None:
    assert low <= lighting_for(Weather.from_partial({"fog_density": fog})).visibility_m <= high


def test_visibility_decreases_with_fog_and_rain() -> None:
    fogs = (0, 10, 30, 60, 90, 100)
    vis = [lighting_for(Weather.from_partial({"fog_density": f})).visibility_m for f in fogs]
    assert all(a > b for a, b in zip(vis, vis[1:], strict=False))
    assert 300 < vis[1] < 500 and 10 < vis[-1] < 14
    rain = lighting_for(Weather.from_partial({"precipitation": 100.0})).visibility_m
    assert 120 < rain < 180


def test_sun_direction_convention() -> None:
    east = lighting_for(Weather.from_partial({"sun_altitude_angle": 0.0, "sun_azimuth_angle": 0.0}))
    north = lighting_for(Weather.from_partial({"sun_altitude_angle": 0.0, "sun_azimuth_angle": 90.0}))
    np.testing.assert_allclose(east.sun_direction, (1.0, 0.0, 0.0), atol=1e-9)
    np.testing.assert_allclose(north.sun_direction, (0.0, 1.0, 0.0), atol=1e-9)
    sunset = lighting_for(Weather.from_partial({"sun_altitude_angle": 3.0, "cloudiness": 0.0}))
    assert sunset.sun_color[2] < 0.6 * sunset.sun_color[0]  # warm, orange light at sunset


def test_clouds_dim_sun_and_shadows() -> None:
    clear = lighting_for(Weather.from_partial({"cloudiness": 0.0}))
    overcast = lighting_for(Weather.from_partial({"cloudiness": 100.0}))
    assert sum(overcast.sun_color) < 0.3 * sum(clear.sun_color)
    assert overcast.shadow_darkness < 0.05 < clear.shadow_darkness
    zen = np.array(overcast.sky_zenith)
    assert zen.max() - zen.min() < 0.1  # grey


def test_rejects_wrong_shapes() -> None:
    comp = WeatherCompositor(W, H, FOV, 0)
    wx = Weather.default()
    with pytest.raises(ValueError):
        comp.apply(np.zeros((10, 10, 3), np.uint8), np.zeros((H, W), np.float32), np.zeros((H, W), np.uint8),
                   wx, lighting_for(wx), 0.0, 0.0, 0)


@pytest.mark.parametrize("partial", [
    {**NOON, "fog_density": 100.0},
    {**NOON, "fog_density": 60.0, "precipitation": 100.0, "precipitation_deposits": 90.0},
    {"sun_altitude_angle": -30.0, "fog_density": 80.0, "precipitation": 40.0},
    {"sun_altitude_angle": 4.0, "sun_azimuth_angle": 0.0, "fog_density": 60.0, "precipitation": 70.0},
])
def test_exp_floor_leaves_every_pixel_as_it_was(monkeypatch, partial) -> None:
    """The optical depth is floored at -87 before cv2.exp (OpenCV's fast path, weather_effects._EXP_FLOOR);
    the frame equals the unfloored one bit for bit, in fog thick enough that far pixels pass the floor."""
    from genesis_rl.sim.lite.render import weather_effects

    wx = Weather.from_partial(partial)
    light = lighting_for(wx)
    assert (light.fog_extinction + light.rain_extinction) * 1000.0 > 87.0  # the sky's depth passes the floor
    floored = _render(wx, step=3)
    monkeypatch.setattr(weather_effects, "_EXP_FLOOR", np.float32(-np.inf))
    np.testing.assert_array_equal(floored, _render(wx, step=3))


def test_camera_vignetting_and_exposure() -> None:
    """Corners darker than the centre on a flat grey frame; exposure 1 at noon, brighter in dim light."""
    flat = np.full((H, W, 3), 120, np.uint8)
    depth = np.full((H, W), 5.0, np.float32)
    lab = np.full((H, W), L.ROAD, np.uint8)
    wx = Weather.from_partial(NOON)
    out = WeatherCompositor(W, H, FOV, 1).apply(flat, depth, lab, wx, lighting_for(wx), 0.0, 0.0, 0)
    lum = _lum(out.astype(np.float64))
    centre, corner = lum[H // 2 - 8 : H // 2 + 8, W // 2 - 8 : W // 2 + 8].mean(), lum[:12, :12].mean()
    assert corner < 0.92 * centre
    assert exposure_gain(0.81) == pytest.approx(1.0)
    assert 1.0 < exposure_gain(0.3) < exposure_gain(0.03) <= weather_effects.EXPOSURE_RANGE[1]


def test_camera_tone_contrast_in_daylight_only() -> None:
    """The tone curve steepens mid-tones at noon and leaves a night frame's dark values alone."""
    noon, night = tone_curve(0.81).astype(int), tone_curve(0.03).astype(int)
    assert noon[200] > 200 and noon[60] < 60
    assert (night == np.arange(256)).all()
