"""The nominal model: what an episode of natural driving inside the ODD draws (docs/estimation.md).

An episode's random inputs are its scene, the start of the *held* knobs (those natural dynamics cannot move
within an episode: the sun's altitude and its bearing from the ego's heading, i.e. the time of day and the
road's direction) and one action per step for every knob (the weather's noise). Everything else (the action
limits per second, the knob ranges, keeping the weather inside the ODD, the simulator) is a deterministic
function of those inputs, the same under the nominal model and under any proposal, so a likelihood ratio taken
on the inputs is exact whatever those functions do (clamps and boundaries included).

The default model: the scene uniform over the catalog; each held knob uniform over the range the ODD allows
(the sun's altitude over the ODD's light classes, e.g. 0-90 deg by day; the bearing over the full circle,
so the sun is as likely ahead as behind); every step's action uniform in [-1, 1] on each knob, what the
``random`` adversary plays (the weather wanders at up to its natural rate); the other knobs start at the
member's start weather (clear). A user replaces the start ranges with a TOML file (``--nominal``), e.g.
narrowed to the hours their fleet drives.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.world.actor_knobs import ACTOR_KNOBS, TrafficConditions
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.odd.conditions import ConditionsModel
from genesis_rl.world.odd.domain import ODD

#: the sun's azimuth is drawn as its bearing from the ego's heading at the episode's start [deg]
BEARING = "sun_bearing"
#: the lead's braking event (members that turn ``lead_decel``): when it starts [s into the episode] and how hard
#: the lead brakes [m/s^2]. Drawn at the start like a held knob, so its likelihood ratio is two numbers, not one
#: per step (NADE's way: tilt the rare manoeuvre, not the noise)
BRAKE_ONSET = "lead_brake_onset_s"
BRAKE_DECEL = "lead_brake_decel"
EVENTS = (BRAKE_ONSET, BRAKE_DECEL)
#: the nominal mean of the lead's braking [m/s^2] in an episode: an exponential, so most episodes brake gently
#: and a hard stop is rare: 1 episode in 150 brakes at 3 m/s^2 or harder, 1 in 800 at 4, 1 in 22,000 at
#: Euro NCAP CCRb's hard 6. Assumed, not fitted (docs/estimation.md says how to substitute a distribution fitted
#: to naturalistic data, e.g. highD's); chosen so that latency_braking's rate falls in the 1e-3..1e-2 an
#: episode where crude Monte Carlo can still check an estimate
LEAD_BRAKE_MEAN = 0.6


@dataclass(frozen=True)
class StartRange:
    """One start variable on [low, high] (a held knob, ``sun_bearing`` or a braking event's): uniform, or with
    ``mean`` an exponential of that mean above ``low``, truncated at ``high`` (rare values of an event)."""

    name: str
    low: float
    high: float
    mean: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low < self.high):
            raise UserInputError(f"nominal start '{self.name}': low = {self.low}, high = {self.high}; allowed: "
                                 "finite numbers with low < high")
        if self.mean is not None and not (math.isfinite(self.mean) and self.mean > 0):
            raise UserInputError(f"nominal start '{self.name}': mean = {self.mean}; allowed: a number > 0 (an "
                                 "exponential's mean above low), or leave it out (uniform)")

    @property
    def width(self) -> float:
        return self.high - self.low

    def log_density(self, x: float) -> float:
        if not self.low <= x <= self.high:
            return -math.inf
        if self.mean is None:
            return -math.log(self.width)
        rate = 1.0 / self.mean
        return math.log(rate) - rate * (x - self.low) - math.log(-math.expm1(-rate * self.width))

    def sample(self, rng: np.random.Generator) -> float:
        u = float(rng.uniform())
        if self.mean is None:
            return self.low + u * self.width
        # the inverse of the truncated exponential's distribution function
        return float(min(self.high, self.low - self.mean * math.log1p(u * math.expm1(-self.width / self.mean))))

    def to_json(self) -> list[float]:
        return [self.low, self.high] if self.mean is None else [self.low, self.high, self.mean]


@dataclass(frozen=True)
class NominalModel:
    """The start ranges of the held knobs and the per-step action noise (uniform on [-1, 1])."""

    starts: tuple[StartRange, ...]
    action_dim: int

    def start_log_density(self, values: Mapping[str, float]) -> float:
        """log p of a start (-inf outside the ranges)."""
        return float(sum(r.log_density(values[r.name]) for r in self.starts))

    def sample_start(self, rng: np.random.Generator) -> dict[str, float]:
        return {r.name: r.sample(rng) for r in self.starts}

    @property
    def has_braking_event(self) -> bool:
        return any(r.name == BRAKE_DECEL for r in self.starts)

    def sample_actions(self, rng: np.random.Generator, steps: int) -> np.ndarray:
        """Every step's action: the weather's noise, the same stream under any start proposal."""
        return rng.uniform(-1.0, 1.0, (steps, self.action_dim)).astype(np.float32)

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {"starts": {r.name: r.to_json() for r in self.starts},
                                  "step_actions": "uniform [-1, 1]", "scene": "uniform over the catalog"}
        if self.has_braking_event:
            out["step_actions"] = ("uniform [-1, 1], but lead_decel follows the braking event: 0 until its onset, "
                                   "then up to its deceleration at the knob's natural rate")
        return out


def inside_interval(odd: ODD | None, start: Weather, knob: str, model: ConditionsModel, grid: int = 721
                    ) -> tuple[float, float]:
    """The values of ``knob`` at which ``start`` (its other knobs as they are) lies inside the ODD, as one
    interval: a grid over the knob's range finds it, bisection sharpens its ends. Refused where the inside
    values are not one interval (give the range in a --nominal file)."""
    spec = KNOBS[knob]
    if odd is None:
        return spec.low, spec.high

    def inside(v: float) -> bool:
        w = Weather({**start.values, knob: v})
        return odd.contains(model.conditions(w, None), w)

    xs = np.linspace(spec.low, spec.high, grid)
    ok = np.array([inside(float(v)) for v in xs])
    if not ok.any():
        raise UserInputError(f"no value of {knob} puts the start inside the ODD '{odd.name}'")
    first, last = int(np.argmax(ok)), int(len(ok) - 1 - np.argmax(ok[::-1]))
    if not ok[first:last + 1].all():
        raise UserInputError(f"the values of {knob} inside the ODD '{odd.name}' are not one interval; give its "
                             "range in a --nominal file")

    def edge(out_v: float, in_v: float) -> float:  # the inside value nearest the boundary
        for _ in range(40):
            mid = (out_v + in_v) / 2
            out_v, in_v = (out_v, mid) if inside(mid) else (mid, in_v)
        return in_v

    low = float(xs[first]) if first == 0 else edge(float(xs[first - 1]), float(xs[first]))
    high = float(xs[last]) if last == grid - 1 else edge(float(xs[last + 1]), float(xs[last]))
    return low, high


def default_starts(held: Sequence[str], odd: ODD | None, start: Weather, model: ConditionsModel,
                   turned: Sequence[str] = (), episode_s: float | None = None) -> tuple[StartRange, ...]:
    """Uniform over what the ODD allows at the start weather: each held knob over its inside interval (the
    sun's altitude by the ODD's light classes, road water by its road states), the sun's bearing over the
    full circle. The ranges form a box: whether a held knob's start is inside depends on that knob alone at a
    clear start (glare, the one condition that mixes two, needs the heading: steps with it are outside the
    ODD and cannot fail inside it). A member that turns ``lead_decel`` adds the lead's braking event: its onset
    uniform over the episode, its deceleration exponential (mean ``LEAD_BRAKE_MEAN``) up to the strongest the
    ODD releases."""
    out = []
    for name in held:
        if name == "sun_azimuth_angle":
            out.append(StartRange(BEARING, -180.0, 180.0))
        else:
            out.append(StartRange(name, *inside_interval(odd, start, name, model)))
    if "lead_decel" in turned and episode_s is not None:
        strongest = (odd.traffic or TrafficConditions()).max_lead_decel if odd is not None else \
            ACTOR_KNOBS["lead_decel"].high
        out += [StartRange(BRAKE_ONSET, 0.0, float(episode_s)),
                StartRange(BRAKE_DECEL, 0.0, float(min(strongest, ACTOR_KNOBS["lead_decel"].high)), LEAD_BRAKE_MEAN)]
    return tuple(out)


def start_names(held: Sequence[str]) -> list[str]:
    """The start variables of ``held`` knobs (the sun's azimuth is drawn as its bearing)."""
    return [BEARING if k == "sun_azimuth_angle" else k for k in held]


def load_starts(path: Path) -> tuple[StartRange, ...]:
    """A ``--nominal`` file: ``[start.NAME]`` with ``low`` and ``high`` for each held knob (``sun_bearing``, in
    [-180, 180], for the sun's azimuth); :func:`check_starts` compares the names with the held knobs."""
    from genesis_rl.core.parsing import loads_toml, read_toml_text  # size and depth limits: a hostile file is one line

    data = loads_toml(read_toml_text(path, "--nominal"), f"--nominal '{path}'")
    table = data.get("start")
    if not isinstance(table, dict) or not table or set(data) != {"start"}:
        raise UserInputError(f"--nominal '{path}': give one [start.NAME] table per held knob, nothing else")
    out = []
    for name, entry in table.items():
        if name not in (BEARING, *EVENTS) and name not in KNOBS:
            raise UserInputError(f"--nominal '{path}': start.{name} is not a knob; allowed: {BEARING}, "
                                 f"{', '.join(EVENTS)}, {', '.join(KNOBS)}")
        keys = set(entry) if isinstance(entry, dict) else set()
        if not {"low", "high"} <= keys <= {"low", "high", "mean"}:
            raise UserInputError(f"--nominal '{path}': start.{name} needs low and high, and may give mean (an "
                                 "exponential's mean above low: rare large values); nothing else")
        assert isinstance(entry, dict)
        if not all(isinstance(entry[k], int | float) and not isinstance(entry[k], bool) for k in keys):
            raise UserInputError(f"--nominal '{path}': start.{name}: {', '.join(sorted(keys))} must be numbers")
        r = StartRange(name, float(entry["low"]), float(entry["high"]),
                       float(entry["mean"]) if "mean" in entry else None)
        bound = (-180.0, 180.0) if name == BEARING else (0.0, 3600.0) if name == BRAKE_ONSET else \
            (KNOBS["lead_decel"].low, KNOBS["lead_decel"].high) if name == BRAKE_DECEL else \
            (KNOBS[name].low, KNOBS[name].high)
        if r.low < bound[0] or r.high > bound[1]:
            raise UserInputError(f"--nominal '{path}': start.{name} = [{r.low:g}, {r.high:g}] leaves the allowed "
                                 f"[{bound[0]:g}, {bound[1]:g}]")
        out.append(r)
    return tuple(out)


def check_starts(starts: Sequence[StartRange], held: Sequence[str], turned: Sequence[str] = ()
                 ) -> tuple[StartRange, ...]:
    """``starts`` with the held knobs first, in their order, then any other knob the agent turns (a
    climatological start of fog or rain: drawn, then moved by the step noise), then the lead's braking event
    (both its onset and its deceleration, for a member that turns ``lead_decel``); refused, naming the lists,
    when a held knob is missing or a name is none of these."""
    names = start_names(held)
    given = {r.name: r for r in starts}
    events = [n for n in EVENTS if n in given]
    extra = [n for n in given if n not in names and n not in EVENTS]
    may_add = [k for k in turned if k not in held and k != "lead_decel"]
    bad_events = events and (len(events) != len(EVENTS) or "lead_decel" not in turned)
    if not set(names) <= set(given) or any(n not in may_add for n in extra) or bad_events:
        allowed = f"{may_add}" + (f", and the braking event {list(EVENTS)} (both)" if "lead_decel" in turned else
                                   f" (the braking event {list(EVENTS)} needs a member that turns lead_decel)")
        raise UserInputError(f"--nominal: the start ranges name {sorted(given)}; this member needs every held knob "
                             f"{names}, and may add knobs it turns {allowed}")
    return tuple(given[n] for n in [*names, *extra, *events])
