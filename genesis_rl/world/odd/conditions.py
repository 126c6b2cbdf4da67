"""Driving conditions in physical units, read off a weather: what an operational design domain constrains.

An ODD (ISO 34503, ASAM OpenODD) is written in quantities a safety engineer can check against a weather
report, not in a simulator's knobs: meteorological visibility [m], rain rate [mm/h], the road's state, the
light and whether the sun glares into the camera. Each backend maps its knobs to these quantities in one
place, a :class:`ConditionsModel`:

* ``lite`` exactly from its renderer's own model: the visibility is the one its Koschmieder fog and rain
  extinction give (``world.visibility``, which lite's renderer draws); its rain, road water and sun knobs
  have no physical unit of their own, so the tables below fix one, by the meteorological categories of rain
  rate (AMS glossary: light < 2.5 mm/h, moderate < 7.6, heavy < 50, violent above) and the twilight definitions.
* ``carla`` by a documented approximation (the same tables; CARLA's fog also starts at ``fog_distance``);
  replace it with ``register_conditions_model("carla", MyModel())`` where your server's look differs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from genesis_rl.world.knobs import Weather
from genesis_rl.world.visibility import KOSCHMIEDER, extinctions

ROAD_STATES = ("dry", "damp", "wet", "standing_water")
LIGHTS = ("day", "twilight", "night")

#: lite precipitation [%] -> rain rate [mm/h], linear between the points (AMS category bounds at 30 and 50 %).
RAIN_RATE_TABLE: tuple[tuple[float, float], ...] = ((0.0, 0.0), (10.0, 0.5), (30.0, 2.5), (50.0, 7.6),
                                                    (75.0, 20.0), (100.0, 50.0))
#: sun altitude [deg] at and above which it is day; below TWILIGHT_END_DEG it is night (nautical twilight ends)
DAY_FROM_DEG = 0.0
TWILIGHT_END_DEG = -12.0
#: glare: the sun at most this high [deg] and within this angle of the camera's heading [deg], under
#: an effective cloud cover below GLARE_MAX_COVER (lite draws its bloom and veil in the same cone)
GLARE_MAX_ALTITUDE_DEG = 25.0
GLARE_HALF_ANGLE_DEG = 30.0
GLARE_MAX_COVER = 0.7


@dataclass(frozen=True, slots=True)
class Conditions:
    """One step's conditions: visibility [m], rain rate [mm/h], road state, light, sun glare."""

    visibility_m: float
    rain_mm_h: float
    road_state: str
    light: str
    sun_glare: bool

    def as_dict(self) -> dict[str, float | str | bool]:
        return {"visibility_m": self.visibility_m, "rain_mm_h": self.rain_mm_h, "road_state": self.road_state,
                "light": self.light, "sun_glare": self.sun_glare}


def _interp(table: tuple[tuple[float, float], ...], x: float) -> float:
    xs, ys = zip(*table, strict=True)
    x = min(max(x, xs[0]), xs[-1])
    for (x0, y0), (x1, y1) in zip(table, table[1:], strict=False):
        if x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return ys[-1]


def rain_rate_mm_h(precipitation: float) -> float:
    return _interp(RAIN_RATE_TABLE, precipitation)


def precipitation_for_rain_rate(rain_mm_h: float) -> float:
    """The precipitation knob [%] whose rain rate is ``rain_mm_h`` (the inverse of :func:`rain_rate_mm_h`)."""
    return _interp(tuple((r, p) for p, r in RAIN_RATE_TABLE), rain_mm_h)


def road_state(deposits: float, wetness: float) -> str:
    """Standing water needs water on the road (lite draws puddles from deposits); wetness alone wets it."""
    if deposits >= 60.0:
        return "standing_water"
    level = max(deposits, wetness)
    return "wet" if level >= 25.0 else "damp" if level >= 5.0 else "dry"


def light_of(sun_altitude_deg: float) -> str:
    return "day" if sun_altitude_deg >= DAY_FROM_DEG else "twilight" if sun_altitude_deg >= TWILIGHT_END_DEG \
        else "night"


def sun_glare(weather: Weather, camera_heading_deg: float | None, cloud_cover: float) -> bool:
    """A low sun near the camera's heading (both counter-clockwise from east); no heading known: no glare."""
    alt = float(weather["sun_altitude_angle"])
    if camera_heading_deg is None or not 0.0 <= alt <= GLARE_MAX_ALTITUDE_DEG or cloud_cover >= GLARE_MAX_COVER:
        return False
    off = (float(weather["sun_azimuth_angle"]) - camera_heading_deg + 180.0) % 360.0 - 180.0
    return abs(off) <= GLARE_HALF_ANGLE_DEG


class ConditionsModel:
    """Maps a weather (and the camera's heading, for glare) to :class:`Conditions`; one per backend.

    ``visibility_range_m`` is the visibility the backend can show, clearest last: an ODD whose visibility
    bounds miss it is refused."""

    name = "lite"
    visibility_range_m: tuple[float, float]

    def __init__(self) -> None:
        clear = Weather.default().replace(fog_density=0.0, precipitation=0.0)
        dense = Weather.default().replace(fog_density=100.0, precipitation=100.0)
        self.visibility_range_m = (self.visibility_m(dense), self.visibility_m(clear))

    def visibility_m(self, weather: Weather) -> float:
        """Exactly the visibility lite renders: its fog and rain extinction (``lighting_for`` uses the same)."""
        fog, rain = extinctions(weather["fog_density"], weather["precipitation"])
        return KOSCHMIEDER / (fog + rain)

    def cloud_cover(self, weather: Weather) -> float:
        cloud, rain = float(weather["cloudiness"]) / 100.0, float(weather["precipitation"]) / 100.0
        return 1.0 - (1.0 - cloud) * (1.0 - 0.9 * rain)  # as lite's lighting: rain comes from clouds

    def conditions(self, weather: Weather, camera_heading_deg: float | None = None) -> Conditions:
        return Conditions(
            visibility_m=round(self.visibility_m(weather), 3),
            rain_mm_h=round(rain_rate_mm_h(float(weather["precipitation"])), 3),
            road_state=road_state(float(weather["precipitation_deposits"]), float(weather["wetness"])),
            light=light_of(float(weather["sun_altitude_angle"])),
            sun_glare=sun_glare(weather, camera_heading_deg, self.cloud_cover(weather)),
        )


class CarlaConditionsModel(ConditionsModel):
    """An approximation for CARLA: lite's fog and rain extinction, with the fog starting ``fog_distance``
    metres from the camera (CARLA's exponential height fog is not a Koschmieder medium)."""

    name = "carla"

    def visibility_m(self, weather: Weather) -> float:
        return float(weather["fog_distance"]) + super().visibility_m(weather)


CONDITIONS_MODELS: dict[str, Callable[[], ConditionsModel]] = {"lite": ConditionsModel, "carla": CarlaConditionsModel}
_CACHE: dict[str, ConditionsModel] = {}


def register_conditions_model(backend: str, factory: Callable[[], ConditionsModel]) -> None:
    """Use ``factory()`` to read the conditions of ``backend``'s weathers (a plug-in backend, or CARLA with
    a calibration of one's own)."""
    CONDITIONS_MODELS[backend] = factory
    _CACHE.pop(backend, None)


def conditions_model(backend: str) -> ConditionsModel:
    """The backend's model; a plug-in backend without one reads its weather as lite does."""
    if backend not in _CACHE:
        _CACHE[backend] = CONDITIONS_MODELS.get(backend, ConditionsModel)()
    return _CACHE[backend]

