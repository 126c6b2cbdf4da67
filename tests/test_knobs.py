import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.world.knobs import KNOBS, PAPER_KNOBS, KnobActionMapper, Weather, parse_weather


def test_five_percent_limit_holds_for_any_action():
    mapper = KnobActionMapper()
    rng = np.random.default_rng(0)
    w = Weather.default()
    for _ in range(2000):
        action = rng.normal(scale=5.0, size=5)  # far outside [-1, 1] on purpose
        new = mapper.apply(w, action)
        for name in PAPER_KNOBS:
            spec = KNOBS[name]
            diff = abs(new[name] - w[name])
            if spec.wraps:
                diff = min(diff, spec.span - diff)
            assert diff <= 0.05 * spec.span + 1e-9
            assert spec.low <= new[name] <= spec.high
        w = new


def test_extreme_action_moves_exactly_five_percent_and_azimuth_wraps():
    mapper = KnobActionMapper()
    w = Weather.from_partial({"fog_density": 50, "sun_azimuth_angle": 355})
    new = mapper.apply(w, np.array([1e9, -1e9, 1, 1, 1]))
    assert new["fog_density"] == pytest.approx(55.0)
    assert new["precipitation"] == 0.0  # clipped at the bottom of its range
    assert new["sun_azimuth_angle"] == pytest.approx(13.0)  # 355 + 18 wraps to 13


def test_nan_action_is_rejected_with_the_knob_named():
    with pytest.raises(ValueError, match="precipitation"):
        KnobActionMapper().apply(Weather.default(), np.array([0, np.nan, 0, 0, 0]))


def test_disabled_knobs_never_move():
    mapper = KnobActionMapper(disabled=("fog_density", "precipitation"))
    w = Weather.default()
    rng = np.random.default_rng(1)
    for _ in range(200):
        w = mapper.apply(w, rng.uniform(-1, 1, 5))
    assert w["fog_density"] == 0 and w["precipitation"] == 0
    assert w["sun_altitude_angle"] != Weather.default()["sun_altitude_angle"]


@pytest.mark.parametrize(
    "text, match",
    [("fog=3", "unknown knob 'fog'"), ("fog_density=300", "allowed 0..100"), ("fog_density=abc", "must be a number"),
     ("sunny", "neither KNOB=VALUE nor a preset")],
)
def test_bad_weather_strings_name_the_field(text, match):
    with pytest.raises(UserInputError, match=match):
        parse_weather(text)


def test_weather_string_and_preset():
    w = parse_weather("heavy_rain_night,fog_density=30")
    assert w["fog_density"] == 30 and w["precipitation"] == 90 and w["sun_altitude_angle"] == -40
