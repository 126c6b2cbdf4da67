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
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from genesis_rl.errors import UserInputError
from genesis_rl.knobs import KNOBS, Weather
from genesis_rl.odd.conditions import ConditionsModel
from genesis_rl.odd.domain import ODD

#: the sun's azimuth is drawn as its bearing from the ego's heading at the episode's start [deg]
BEARING = "sun_bearing"
@dataclass(frozen=True)
class StartRange:
    """One start variable drawn uniformly on [low, high] (a held knob, or ``sun_bearing``)."""

    name: str
    low: float
    high: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low < self.high):
            raise UserInputError(f"nominal start '{self.name}': low = {self.low}, high = {self.high}; allowed: "
                                 "finite numbers with low < high")

    @property
    def width(self) -> float:
        return self.high - self.low


@dataclass(frozen=True)
class NominalModel:
    """The start ranges of the held knobs and the per-step action noise (uniform on [-1, 1])."""

    starts: tuple[StartRange, ...]
    action_dim: int

    def start_log_density(self, values: Mapping[str, float]) -> float:
        """log p of a start (uniform: the same everywhere inside the ranges, -inf outside)."""
        inside = all(r.low <= values[r.name] <= r.high for r in self.starts)
        return -sum(math.log(r.width) for r in self.starts) if inside else -math.inf

    def sample_start(self, rng: np.random.Generator) -> dict[str, float]:
        return {r.name: float(rng.uniform(r.low, r.high)) for r in self.starts}

    def sample_actions(self, rng: np.random.Generator, steps: int) -> np.ndarray:
        """Every step's action: the weather's noise, the same stream under any start proposal."""
        return rng.uniform(-1.0, 1.0, (steps, self.action_dim)).astype(np.float32)

    def to_json(self) -> dict[str, object]:
        return {"starts": {r.name: [r.low, r.high] for r in self.starts}, "step_actions": "uniform [-1, 1]",
                "scene": "uniform over the catalog"}


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


def default_starts(held: Sequence[str], odd: ODD | None, start: Weather, model: ConditionsModel
                   ) -> tuple[StartRange, ...]:
    """Uniform over what the ODD allows at the start weather: each held knob over its inside interval (the
    sun's altitude by the ODD's light classes, road water by its road states), the sun's bearing over the
    full circle. The ranges form a box: whether a held knob's start is inside depends on that knob alone at a
    clear start (glare, the one condition that mixes two, needs the heading: steps with it are outside the
    ODD and cannot fail inside it)."""
    out = []
    for name in held:
        if name == "sun_azimuth_angle":
            out.append(StartRange(BEARING, -180.0, 180.0))
        else:
            out.append(StartRange(name, *inside_interval(odd, start, name, model)))
    return tuple(out)


def start_names(held: Sequence[str]) -> list[str]:
    """The start variables of ``held`` knobs (the sun's azimuth is drawn as its bearing)."""
    return [BEARING if k == "sun_azimuth_angle" else k for k in held]


def load_starts(path: Path) -> tuple[StartRange, ...]:
    """A ``--nominal`` file: ``[start.NAME]`` with ``low`` and ``high`` for each held knob (``sun_bearing``, in
    [-180, 180], for the sun's azimuth); :func:`check_starts` compares the names with the held knobs."""
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise UserInputError(f"--nominal '{path}': not TOML ({err})") from None
    table = data.get("start")
    if not isinstance(table, dict) or not table or set(data) != {"start"}:
        raise UserInputError(f"--nominal '{path}': give one [start.NAME] table per held knob, nothing else")
    out = []
    for name, entry in table.items():
        if name != BEARING and name not in KNOBS:
            raise UserInputError(f"--nominal '{path}': start.{name} is not a knob; allowed: {BEARING}, "
                                 f"{', '.join(KNOBS)}")
        if not isinstance(entry, dict) or set(entry) != {"low", "high"}:
            raise UserInputError(f"--nominal '{path}': start.{name} needs low and high, nothing else")
        if not all(isinstance(entry[k], int | float) and not isinstance(entry[k], bool) for k in ("low", "high")):
            raise UserInputError(f"--nominal '{path}': start.{name}: low and high must be numbers")
        r = StartRange(name, float(entry["low"]), float(entry["high"]))
        bound = (-180.0, 180.0) if name == BEARING else (KNOBS[name].low, KNOBS[name].high)
        if r.low < bound[0] or r.high > bound[1]:
            raise UserInputError(f"--nominal '{path}': start.{name} = [{r.low:g}, {r.high:g}] leaves the allowed "
                                 f"[{bound[0]:g}, {bound[1]:g}]")
        out.append(r)
    return tuple(out)


def check_starts(starts: Sequence[StartRange], held: Sequence[str], turned: Sequence[str] = ()
                 ) -> tuple[StartRange, ...]:
    """``starts`` with the held knobs first, in their order, then any other knob the agent turns (a
    climatological start of fog or rain: drawn, then moved by the step noise); refused, naming both lists, when a
    held knob is missing or a name is neither."""
    names = start_names(held)
    given = {r.name: r for r in starts}
    extra = [n for n in given if n not in names]
    if not set(names) <= set(given) or any(n not in turned or n in held for n in extra):
        raise UserInputError(f"--nominal: the start ranges name {sorted(given)}; this member needs every held knob "
                             f"{names}, and may add knobs it turns {[k for k in turned if k not in held]}")
    return tuple(given[n] for n in [*names, *extra])
