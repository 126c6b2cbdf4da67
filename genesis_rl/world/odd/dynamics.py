"""How fast weather may change, and how likely a weather trajectory is.

Two dynamics presets bound each knob's change:

* ``paper``: at most ``max_step_fraction`` (5 %) of the knob's range per 0.05 s step, the paper's limit.
  Fog goes from clear to its densest in one second.
* ``natural``: at most :data:`NATURAL_RATES` per simulated second, what outdoor weather does (docs/odd.md
  gives the sources): the sun moves 0.25 degrees a minute (so within an episode it is set at the start and
  held), a car drives into a fog bank within seconds, rain sets in over tens of seconds, water builds up
  on the road over minutes. The limit is per second, so it holds at any step length.

The weather model behind the naturalness score (Adaptive Stress Testing's likelihood of a disturbance
sequence) is a random walk: each controlled knob's change over ``dt`` seconds is Gaussian with standard
deviation ``sigma_k * sqrt(dt)``, with ``sigma_k`` its natural rate, so a one-second change as large as
the natural limit is a one-sigma event. The start weather is uniform over each knob's range. An episode's
log-likelihood is the start term plus every step's transition term, in nats: higher is more natural. Its
*naturalness* is the log-likelihood ratio against the same start with the weather held still (-0.5 sum z^2
over steps and knobs, <= 0; 0: nothing changed): it compares trajectories of different lengths fairly, and
it is what reports rank failures by.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.world.actor_knobs import ACTOR_KNOBS
from genesis_rl.world.knobs import KNOBS

DYNAMICS = ("paper", "natural")

#: the natural preset's largest change per second, in each knob's unit [unit/s]
NATURAL_RATES: dict[str, float] = {
    "fog_density": 4.0,  # into a fog bank at road speed: clear to moderate fog (30 %, ~120 m) in 7.5 s
    "precipitation": 2.0,  # a shower sets in: none to heavy rain (50 %, 7.6 mm/h) in 25 s
    "precipitation_deposits": 0.2,  # water builds on the road over minutes: standing water (60 %) in 5 min
    "wetness": 0.5,  # surfaces wet within a minute or two of rain
    "sun_altitude_angle": 0.25 / 60.0,  # Earth turns 0.25 deg a minute: the sun is set and held
    "sun_azimuth_angle": 0.25 / 60.0,
    "cloudiness": 0.5,  # clouds move in over minutes
    "wind_intensity": 5.0,  # gusts
    "fog_distance": 30.0,  # a fog bank's edge approaches at driving speed [m/s]
}
#: knobs without a rate above (CARLA-only fields, user knobs) may change this fraction of their range a second
DEFAULT_RATE_FRACTION = 0.01


def natural_rate(knob: str) -> float:
    """Largest natural change per second [unit/s]: the table above, an actor knob's declared rate
    (``actor_knobs``), else :data:`DEFAULT_RATE_FRACTION` of the range."""
    if knob in NATURAL_RATES:
        return NATURAL_RATES[knob]
    if KNOBS[knob].is_actor and knob in ACTOR_KNOBS:
        return ACTOR_KNOBS[knob].natural_rate
    return DEFAULT_RATE_FRACTION * KNOBS[knob].span


def max_deltas(knobs: Sequence[str], dynamics: str, dt: float, max_step_fraction: float) -> np.ndarray:
    """Each knob's largest change per step of ``dt`` seconds under ``dynamics``."""
    if dynamics not in DYNAMICS:
        raise UserInputError(f"dynamics = '{dynamics}' is unknown; allowed: {', '.join(DYNAMICS)}")
    if dynamics == "paper":
        return np.array([KNOBS[k].span * max_step_fraction for k in knobs], np.float64)
    return np.array([natural_rate(k) * dt for k in knobs], np.float64)


@dataclass(frozen=True)
class WeatherModel:
    """The random-walk weather model over ``knobs`` (see the module docstring)."""

    knobs: tuple[str, ...]

    @property
    def sigmas(self) -> np.ndarray:
        return np.array([natural_rate(k) for k in self.knobs], np.float64)

    def start_log_likelihood(self) -> float:
        return float(-sum(math.log(KNOBS[k].span) for k in self.knobs))

    def step_z(self, before: Mapping[str, float], after: Mapping[str, float], dt: float) -> np.ndarray:
        """Each knob's change in units of its standard deviation over ``dt``."""
        d = np.array([after[k] - before[k] for k in self.knobs], np.float64)
        for i, k in enumerate(self.knobs):
            if KNOBS[k].wraps:
                span = KNOBS[k].span
                d[i] = (d[i] + span / 2) % span - span / 2
        return d / (self.sigmas * math.sqrt(dt))

    def step_log_likelihood(self, before: Mapping[str, float], after: Mapping[str, float], dt: float) -> float:
        z = self.step_z(before, after, dt)
        norm = np.log(2 * math.pi * self.sigmas**2 * dt)
        return float(-0.5 * np.sum(norm + z * z))

    def surprise(self, before: Mapping[str, float], after: Mapping[str, float], dt: float) -> float:
        """The step's log-likelihood less that of no change (-0.5 sum z^2 <= 0): the reward's naturalness term."""
        z = self.step_z(before, after, dt)
        return float(-0.5 * np.sum(z * z))

    def naturalness(self, trajectory: Sequence[Mapping[str, float]], dt: float) -> float:
        """The trajectory's log-likelihood ratio against held weather [nats, <= 0]."""
        return float(sum(self.surprise(a, b, dt) for a, b in zip(trajectory, trajectory[1:], strict=False)))

    def log_likelihood(self, trajectory: Sequence[Mapping[str, float]], dt: float) -> float:
        """A trajectory's log-likelihood: the start (its first weather) and every change after it [nats]."""
        if not trajectory:
            return 0.0
        total = self.start_log_likelihood()
        for a, b in zip(trajectory, trajectory[1:], strict=False):
            total += self.step_log_likelihood(a, b, dt)
        return total
