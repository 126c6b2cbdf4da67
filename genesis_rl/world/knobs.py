"""Parametric knobs: the weather the agent turns, named and ranged as CARLA's ``carla.WeatherParameters``.

One agent drives either backend because both read the same knob names. The agent's action is always
Box(-1, 1); :class:`KnobActionMapper` scales it so that one step moves a knob by at most a fixed fraction
of its range (the paper's naturalness limit, 5%), clips to the range and wraps angles that wrap.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError

#: A lite render hook: ``hook(rgb, depth, value) -> rgb`` applied to the finished camera image (uint8, H x W x
#: 3; depth in metres), after the built-in weather pass, when the knob is not at its default.
FrameHook = Callable[[np.ndarray, np.ndarray, float], np.ndarray]


@dataclass(frozen=True)
class KnobSpec:
    """A weather parameter, declared once: its range, unit and default, whether it wraps around (azimuth
    does), how each backend realises it, and the values the contact sheet sweeps.

    ``carla_field``: the ``carla.WeatherParameters`` field it sets (None: CARLA has no such field).
    ``lite``: how the embedded simulator realises it: ``lighting`` (sun, sky, clouds, fog extinction),
    ``weather_pass`` (rain streaks, wet road, fog distance), ``hook`` (``frame_hook``, a user's own effect),
    ``traffic`` (an actor knob: the traffic model acts on it, see ``genesis_rl.world.actor_knobs``) or ``none`` (a
    CARLA-only field that lite does not draw).
    ``sweep``: the values of its row in ``genesis-rl render --sweep`` (empty: no row), each on top of clear
    noon changed by ``sweep_base``."""

    name: str
    low: float
    high: float
    unit: str
    default: float
    wraps: bool = False
    description: str = ""
    carla_field: str | None = None
    lite: str = "none"
    frame_hook: FrameHook | None = None
    sweep: tuple[float, ...] = ()
    sweep_base: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise UserInputError(f"knob name {self.name!r} must be an identifier, e.g. lens_dirt")
        for end in ("low", "high", "default"):  # within 1e9: a span and a step of it stay finite
            ranges.number(getattr(self, end), f"knob '{self.name}': {end}", -KNOB_MAGNITUDE, KNOB_MAGNITUDE,
                          self.unit)
        if not self.low < self.high:
            raise UserInputError(f"knob '{self.name}': range {self.low}..{self.high} must be finite with low < high")
        if not self.low <= self.default <= self.high:
            raise UserInputError(f"knob '{self.name}': default {self.default} is outside {self.low:g}..{self.high:g}")
        if self.lite not in LITE_EFFECTS:
            raise UserInputError(f"knob '{self.name}': lite = '{self.lite}'; allowed: {', '.join(LITE_EFFECTS)}")
        if (self.lite == "hook") != (self.frame_hook is not None):
            raise UserInputError(f"knob '{self.name}': a frame_hook goes with lite = 'hook', and only with it")
        bad = [v for v in self.sweep if not self.low <= v <= self.high]
        if bad:
            raise UserInputError(f"knob '{self.name}': sweep values {bad} are outside {self.low:g}..{self.high:g}")

    @property
    def span(self) -> float:
        return self.high - self.low

    def fit(self, value: float) -> float:
        """``value`` inside the knob's range: wrapped around for a knob that wraps (the sun's azimuth: -1 is
        359), clipped otherwise."""
        if self.wraps:
            return self.low + (value - self.low) % self.span
        return min(max(value, self.low), self.high)

    @property
    def is_actor(self) -> bool:
        """An actor knob (other road users' behaviour), not a weather one."""
        return self.lite == "traffic"


LITE_EFFECTS = ("lighting", "weather_pass", "hook", "traffic", "none")
#: the largest magnitude a knob's bound may have (CARLA's largest range is 0..360 deg)
KNOB_MAGNITUDE = 1e9
#: a step fraction below this freezes the agent (a knob would need over 1,000 steps to cross its range)
MIN_STEP_FRACTION = 1e-3
_PCT = (0.0, 20.0, 40.0, 60.0, 80.0, 100.0)


def _k(name: str, low: float, high: float, unit: str, default: float, desc: str, wraps: bool = False,
       lite: str = "none", sweep: tuple[float, ...] = (), sweep_base: Mapping[str, float] | None = None) -> KnobSpec:
    return KnobSpec(name, low, high, unit, default, wraps, desc, carla_field=name, lite=lite, sweep=sweep,
                    sweep_base=dict(sweep_base or {}))


#: Every field of carla.WeatherParameters (0.9.16), with CARLA's documented ranges. Unbounded CARLA
#: ranges (fog_distance, fog_falloff, scattering) get a finite range, as a Box action space needs.
#: ``register_knob`` adds a knob of one's own.
KNOBS: dict[str, KnobSpec] = {
    k.name: k
    for k in (
        _k("fog_density", 0, 100, "%", 0, "fog concentration; visibility falls with it (Koschmieder)",
           lite="lighting", sweep=_PCT),
        _k("precipitation", 0, 100, "%", 0, "rain intensity: streaks, lower contrast and visibility",
           lite="weather_pass", sweep=_PCT),
        _k("precipitation_deposits", 0, 100, "%", 0, "water on the road: dark, glossy, puddles",
           lite="weather_pass", sweep=_PCT),
        _k("sun_altitude_angle", -90, 90, "deg", 75, "sun elevation: noon at 90, sunset near 0, night below",
           lite="lighting", sweep=(75, 30, 10, 3, -5, -40)),
        # azimuth only shows with a low sun: its row sweeps it at 12 degrees of altitude
        _k("sun_azimuth_angle", 0, 360, "deg", 45, "sun heading: shadows and glare", wraps=True,
           lite="lighting", sweep=(0, 60, 120, 180, 240, 300), sweep_base={"sun_altitude_angle": 12.0}),
        _k("cloudiness", 0, 100, "%", 5, "cloud cover: dims the sun and greys the sky", lite="lighting"),
        _k("wetness", 0, 100, "%", 0, "wetness of surfaces (darkens them)", lite="weather_pass"),
        _k("wind_intensity", 0, 100, "%", 10, "wind: slants the rain", lite="weather_pass"),
        _k("fog_distance", 0, 200, "m", 0, "distance at which fog starts", lite="weather_pass"),
        _k("fog_falloff", 0, 5, "", 0.2, "fog density falloff with height (CARLA only)"),
        _k("scattering_intensity", 0, 2, "", 1, "light contribution to volumetric fog (CARLA only)"),
        _k("mie_scattering_scale", 0, 5, "", 0.03, "Mie scattering (CARLA only)"),
        _k("rayleigh_scattering_scale", 0, 2, "", 0.0331, "Rayleigh scattering (CARLA only)"),
        _k("dust_storm", 0, 100, "%", 0, "dust storm strength (CARLA only)"),
    )
}


def _actor_knob(name: str) -> KnobSpec:
    """An actor knob the step loop turns like a weather knob: declared once in ``actor_knobs.ACTOR_KNOBS``
    (unit, range, natural rate, source), carried by every :class:`Weather` at its default (the actor does
    nothing unusual), realised by lite's traffic model."""
    from genesis_rl.world.actor_knobs import ACTOR_KNOBS

    a = ACTOR_KNOBS[name]
    return KnobSpec(a.name, a.low, a.high, a.unit, a.default, description=a.description, lite="traffic")


#: Actor knobs that act step by step: ``lead_decel`` > 0 makes the vehicle ahead of the ego brake at
#: that deceleration for as long as it stays > 0; ``cut_in_ttc`` below its default makes a slower neighbour cut
#: in ahead of the ego into a gap of that time-to-collision (``cut_in_relative_speed`` > 0: the neighbour slows
#: to that much below the ego's speed first, so that such a gap comes); two of CARLA TrafficManager's
#: per-vehicle parameters set the surrounding traffic's behaviour (docs/actors.md). The others in
#: ``actor_knobs`` are declared but not yet turned by the step loop.
STEP_ACTOR_KNOBS: tuple[str, ...] = ("lead_decel", "cut_in_ttc", "vehicle_percentage_speed_difference",
                                     "ignore_lights_percentage", "cut_in_relative_speed")
for _name in STEP_ACTOR_KNOBS:
    KNOBS[_name] = _actor_knob(_name)


#: The module that declared each knob added with ``register_knob`` (workers import it again).
KNOB_MODULES: dict[str, str] = {}


def register_knob(spec: KnobSpec) -> KnobSpec:
    """Declare a knob of one's own (in one's module, at import): every weather then carries it at its
    default, the env can turn it (``env.knobs``), records and telemetry store it, ``render --sweep`` shows
    it, and lite draws it through its ``frame_hook``. Records written before it existed replay with it at
    its default. A worker process re-imports the declaring module (see ``evaluation.campaign``)."""
    if spec.name in KNOBS and KNOBS[spec.name] != spec:
        raise UserInputError(f"knob '{spec.name}' is already declared ({KNOBS[spec.name].description!r})")
    KNOBS[spec.name] = spec
    KNOB_MODULES[spec.name] = sys._getframe(1).f_globals.get("__name__", "")  # the declaring module
    return spec


def weather_knob_names() -> tuple[str, ...]:
    """The weather knobs (every knob but the actor knobs), in declaration order."""
    return tuple(n for n, k in KNOBS.items() if not k.is_actor)


def frame_hooks() -> list[KnobSpec]:
    """The knobs with a lite frame hook, in declaration order."""
    return [k for k in KNOBS.values() if k.frame_hook is not None]


#: The paper's five knobs, in the order of the agent's action vector.
PAPER_KNOBS: tuple[str, ...] = (
    "fog_density",
    "precipitation",
    "precipitation_deposits",
    "sun_altitude_angle",
    "sun_azimuth_angle",
)

#: Named weathers for people and tests (names after CARLA's presets where one exists).
PRESETS: dict[str, dict[str, float]] = {
    "clear_noon": {"sun_altitude_angle": 75.0, "sun_azimuth_angle": 45.0},
    "clear_sunset": {"sun_altitude_angle": 5.0, "sun_azimuth_angle": 270.0, "cloudiness": 15.0},
    "dense_fog": {"fog_density": 90.0, "sun_altitude_angle": 40.0, "cloudiness": 60.0},
    "heavy_rain_night": {
        "precipitation": 90.0,
        "precipitation_deposits": 80.0,
        "wetness": 80.0,
        "cloudiness": 90.0,
        "sun_altitude_angle": -40.0,
        "wind_intensity": 40.0,
    },
    "wet_sunset_glare": {
        "precipitation_deposits": 70.0,
        "wetness": 70.0,
        "sun_altitude_angle": 4.0,
        "sun_azimuth_angle": 0.0,
        "cloudiness": 10.0,
    },
    "clear_night": {"sun_altitude_angle": -50.0, "sun_azimuth_angle": 45.0},
}


def knob_spec(name: str) -> KnobSpec:
    try:
        return KNOBS[name]
    except KeyError:
        raise UserInputError(f"unknown knob '{name}'; allowed: {', '.join(KNOBS)}") from None


@dataclass(frozen=True)
class Weather:
    """A full assignment of every knob. Immutable: each step makes a new one."""

    values: Mapping[str, float]

    def __post_init__(self) -> None:
        missing = set(KNOBS) - set(self.values)
        unknown = set(self.values) - set(KNOBS)
        if missing or unknown:
            raise UserInputError(f"weather must set exactly the knobs {list(KNOBS)}; missing {sorted(missing)}, "
                                 f"unknown {sorted(unknown)}")

    @classmethod
    def default(cls) -> Weather:
        return cls({k.name: float(k.default) for k in KNOBS.values()})

    @classmethod
    def from_partial(cls, partial: Mapping[str, float], base: Weather | None = None) -> Weather:
        """Start from ``base`` (clear noon by default) and override some knobs, checking names and ranges."""
        values = dict((base or cls.default()).values)
        for name, value in partial.items():
            spec = knob_spec(name)
            v = float(value)
            if not math.isfinite(v) or not spec.low <= v <= spec.high:
                raise UserInputError(
                    f"knob '{name}' = {value} is out of range; allowed {spec.low:g}..{spec.high:g} {spec.unit}"
                )
            values[name] = v
        return cls(values)

    @classmethod
    def from_recorded(cls, values: Mapping[str, float]) -> Weather:
        """A weather read back from a record or telemetry: knobs it does not name (a knob added after it was
        written) take their defaults; unknown names are errors."""
        unknown = set(values) - set(KNOBS)
        if unknown:
            raise UserInputError(f"recorded weather names unknown knob(s) {sorted(unknown)}; "
                                 f"allowed: {', '.join(KNOBS)}")
        wrong: dict[str, object] = {k: v for k, v in values.items()
                                    if isinstance(v, bool) or not isinstance(v, int | float | str)}
        try:
            if wrong:
                raise ValueError
            read = {k: float(values[k]) if k in values else float(spec.default) for k, spec in KNOBS.items()}
        except (ValueError, OverflowError):  # "fast", true, [1], 10**400: a damaged record or telemetry file
            unreadable = wrong or {k: v for k, v in values.items() if not _parses(v)}
            shown = ", ".join(f"'{k}': {repr(v)[:30]}" for k, v in unreadable.items())
            raise UserInputError(f"recorded weather has knob value(s) that are not numbers {{{shown}}}; "
                                 "expected finite numbers in the knobs' ranges") from None
        bad = {k: v for k, v in read.items() if not math.isfinite(v)}
        if bad:  # JSON's NaN and Infinity parse; a damaged record or telemetry file must not steer the simulator
            raise UserInputError(f"recorded weather has non-finite knob value(s) {bad}; expected finite numbers")
        outside = {k: v for k, v in read.items() if not KNOBS[k].low <= v <= KNOBS[k].high}
        if outside:  # a fog density of 1e308 would reach the renderer and the ODD labels as it is
            k, v = next(iter(outside.items()))
            raise UserInputError(f"recorded weather has knob value(s) outside their range {outside}; e.g. '{k}' "
                                 f"= {v!r}, allowed {KNOBS[k].low:g}..{KNOBS[k].high:g} {KNOBS[k].unit}")
        return cls(read)

    @classmethod
    def preset(cls, name: str) -> Weather:
        if name not in PRESETS:
            raise UserInputError(f"unknown weather preset '{name}'; allowed: {', '.join(PRESETS)}")
        return cls.from_partial(PRESETS[name])

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def replace(self, **changes: float) -> Weather:
        return Weather.from_partial(changes, base=self)

    def vector(self, names: Sequence[str]) -> np.ndarray:
        return np.array([self.values[n] for n in names], dtype=np.float64)

    def normalized(self, names: Sequence[str]) -> np.ndarray:
        """Knob values scaled to [0, 1] by their ranges (for observations and plots)."""
        return np.array([(self.values[n] - KNOBS[n].low) / KNOBS[n].span for n in names], dtype=np.float32)

    def as_dict(self) -> dict[str, float]:
        return dict(self.values)


def _parses(v: object) -> bool:
    try:
        float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        return False
    return True


def parse_weather(text: str, base: Weather | None = None) -> Weather:
    """Parse ``--weather``: ``fog_density=60,sun_altitude_angle=10`` or a preset name, optionally followed
    by overrides (``heavy_rain_night,fog_density=30``)."""
    text = text.strip()
    if not text:
        return base or Weather.default()
    weather = base or Weather.default()
    overrides: dict[str, float] = {}
    for i, part in enumerate(p.strip() for p in text.split(",")):
        if not part:
            continue
        if "=" not in part:
            if i == 0:
                if part not in PRESETS:
                    raise UserInputError(
                        f"--weather: '{part}' is neither KNOB=VALUE nor a preset; presets: {', '.join(PRESETS)}; "
                        f"knobs: {', '.join(KNOBS)}"
                    )
                weather = Weather.from_partial(PRESETS[part], base=weather)
                continue
            raise UserInputError(f"--weather: malformed item '{part}'; expected KNOB=VALUE, e.g. fog_density=60")
        name, _, raw = part.partition("=")
        name = name.strip()
        if not name:
            raise UserInputError(f"--weather: missing knob name in '{part}'; expected KNOB=VALUE, e.g. fog_density=60")
        if name in overrides:
            raise UserInputError(f"--weather: knob '{name}' is given twice")
        try:
            knob_spec(name)
        except UserInputError as err:
            raise UserInputError(f"--weather: {err}") from None
        try:
            overrides[name] = float(raw)
        except ValueError:
            raise UserInputError(f"--weather: value of '{name}' must be a number, got '{raw}'") from None
    return Weather.from_partial(overrides, base=weather)


class KnobActionMapper:
    """Maps an agent action in [-1, 1]^n to a new weather: each knob moves at most
    ``max_step_fraction`` of its range per step (or ``max_delta`` of its unit); disabled knobs never move."""

    def __init__(
        self,
        knobs: Sequence[str] = PAPER_KNOBS,
        max_step_fraction: float = 0.05,
        disabled: Iterable[str] = (),
        max_delta: Sequence[float] | np.ndarray | None = None,
    ) -> None:
        for name in knobs:
            knob_spec(name)
        if len(set(knobs)) != len(knobs) or not knobs:
            raise UserInputError(f"knobs must be a non-empty list without repeats, got {list(knobs)}")
        disabled = tuple(disabled)
        for name in disabled:
            if name not in knobs:
                raise UserInputError(f"disabled knob '{name}' is not among the controlled knobs {list(knobs)}")
        ranges.number(max_step_fraction, "env.max_step_fraction", MIN_STEP_FRACTION, 1.0,
                      note="of a knob's range per step; the paper's 0.05")
        self.knobs = tuple(knobs)
        self.max_step_fraction = float(max_step_fraction)
        self.disabled = disabled
        specs = [KNOBS[n] for n in self.knobs]
        self._low = np.array([s.low for s in specs])
        self._high = np.array([s.high for s in specs])
        self._wraps = np.array([s.wraps for s in specs])
        active = np.array([n not in disabled for n in self.knobs], dtype=np.float64)
        #: largest change per step of each knob, in the knob's unit (0 for disabled knobs); ``max_delta``
        #: overrides the fraction of the range (``odd.dynamics.max_deltas``: the natural preset's rates)
        per_step = (self._high - self._low) * self.max_step_fraction if max_delta is None else \
            np.asarray(max_delta, np.float64)
        self.max_delta = per_step * active

    @property
    def action_dim(self) -> int:
        return len(self.knobs)

    def deltas(self, action: np.ndarray) -> np.ndarray:
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (self.action_dim,):
            raise ValueError(f"action must have {self.action_dim} entries ({', '.join(self.knobs)}), got {a.shape}")
        if not np.all(np.isfinite(a)):
            bad = [self.knobs[i] for i in np.flatnonzero(~np.isfinite(a))]
            raise ValueError(f"action is not finite (NaN or inf) for knob(s) {bad}")
        return np.clip(a, -1.0, 1.0) * self.max_delta

    def apply(self, weather: Weather, action: np.ndarray) -> Weather:
        old = weather.vector(self.knobs)
        new = old + self.deltas(action)
        span = self._high - self._low
        wrapped = self._low + np.mod(new - self._low, span)
        new = np.where(self._wraps, wrapped, np.clip(new, self._low, self._high))
        values = dict(weather.values)
        values.update({n: float(v) for n, v in zip(self.knobs, new, strict=True)})
        return Weather(values)
