"""Rules and rulebooks in the formalism of Censi et al. (2019), "Liability, ethics and culture-aware
behavior specification using rulebooks".

A rule maps a trajectory (the step records so far, ``genesis_rl.world.step_record.StepRecord``) to a violation
>= 0 (0 = compliant), as a sum of per-step terms, so that the violation can be read step by step (for the
reward) and as a whole (for evaluation). A rulebook is a set of rules with a priority order: two
trajectories compare rule by rule, highest priority first, and the first rule on which they differ decides.

Adding a rule is one small class, in any module::

    class Speeding(Rule):
        name = "speeding"
        unit = "m/s"
        limit: float = 13.9  # parameters are dataclass fields with defaults

        def term(self, record):
            return max(0.0, record.ego.speed - self.limit)

and one line in a rulebook TOML: ``name = "my_package.my_rules:Speeding"`` (or ``@register_rule`` it and
use ``name = "speeding"``). Summaries, reports, records and replays list every rule of the rulebook; an
unknown rule or parameter fails when the file is loaded.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.plugins import load_class
from genesis_rl.world.step_record import StepRecord

RULES: dict[str, type[Rule]] = {}

#: Names a rule may not take: they are columns of an episode's summary row beside the rules' violations.
RESERVED_NAMES = frozenset({
    "policy", "scene", "episode_seed", "steps", "total", "violations", "collision_events", "first_collision_step",
    "collision_speed", "failure_mode", "failure", "labeller_version", "min_gap", "mean_iou", "return", "sim_steps",
    "knobs_mean", "knobs_final", "extra", "seconds", "record", "rss_deficit_sum",
})


def register_rule(cls: type[Rule]) -> type[Rule]:
    """Class decorator: make a rule available to rulebooks by its short ``name``."""
    _as_rule_class(cls, cls.__qualname__)
    RULES[cls.name] = cls
    return cls


def _as_rule_class(cls: type, where: str) -> type[Rule]:
    """Check a rule class and make it a frozen dataclass (its parameters are its fields)."""
    if not (inspect.isclass(cls) and issubclass(cls, Rule)):
        raise UserInputError(f"{where}: {getattr(cls, '__name__', cls)!r} is not a subclass of "
                             "genesis_rl.loop.rules.rulebook.Rule")
    if not isinstance(cls.name, str) or not cls.name.isidentifier():
        raise UserInputError(f"{where}: rule class {cls.__name__} needs a class attribute `name`, an identifier "
                             f"such as 'speeding' (got {cls.name!r})")
    if cls.name in RESERVED_NAMES:
        raise UserInputError(f"{where}: rule name '{cls.name}' is reserved (a column of episode rows); reserved: "
                             f"{', '.join(sorted(RESERVED_NAMES))}")
    if "__dataclass_fields__" not in cls.__dict__:
        dataclasses.dataclass(frozen=True)(cls)
    return cls


def rule_class(spec: str, where: str = "rulebook") -> type[Rule]:
    """A rule class from a registered name (``collision``) or an import path (``package.module:Class``)."""
    if spec in RULES:
        return RULES[spec]
    if ":" not in spec:
        raise UserInputError(f"{where}: unknown rule {spec!r}; allowed: {', '.join(sorted(RULES))} or "
                             "package.module:Class")
    return _as_rule_class(load_class(spec, f"{where}: rule", {}, base=Rule), f"{where}: rule '{spec}'")


class Rule:
    """A rule: ``term(record)`` is one step's contribution (>= 0); the violation is their sum.

    ``unit`` names the violation's unit for tables and plots; ``in_total`` says whether the violation adds
    into an episode's ``total`` score (the paper's collision + proximity, both in m/s; the RSS deficit, in
    metres, is reported beside it). ``param_ranges`` gives a parameter's physical range (a rulebook's value
    outside it is refused when the file is loaded); a parameter without one must be 0 or of a magnitude in
    [1e-9, 1e9]."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    unit: ClassVar[str] = ""
    in_total: ClassVar[bool] = True
    param_ranges: ClassVar[Mapping[str, ranges.Ranged]] = {}

    def term(self, record: StepRecord) -> float:
        raise NotImplementedError

    def violation(self, records: Sequence[StepRecord]) -> float:
        return float(sum(self.term(r) for r in records))

    def params(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    @classmethod
    def import_path(cls) -> str | None:
        """``module:Class`` when the rule is not registered under its name (a plug-in), else None."""
        return None if RULES.get(cls.name) is cls else f"{cls.__module__}:{cls.__qualname__}"


def _positive(rule: Rule) -> None:
    for k, v in rule.params().items():
        if not v > 0:
            raise ValueError(f"{rule.name}.{k} = {v!r} must be a positive number")


@register_rule
class CollisionRule(Rule):
    """a_c: the ego's speed [m/s] at a step where it collides (the paper's collision rule)."""

    name = "collision"
    description = "ego speed at each step with a collision [m/s]"
    unit = "m/s"

    def term(self, record: StepRecord) -> float:
        c = record.collision
        return float(c.speed) if c.collided else 0.0


@register_rule
class ProximityRule(Rule):
    """a_p: the ego's speed [m/s] while the gap to its lead is under ``distance`` metres."""

    name = "proximity"
    description = "ego speed while the gap to the lead vehicle is under the threshold [m/s]"
    unit = "m/s"
    distance: float = 5.0  # [m]
    param_ranges: ClassVar[Mapping[str, ranges.Ranged]] = {"distance": ranges.Ranged(0.1, 1000.0, "m")}

    def __post_init__(self) -> None:
        _positive(self)

    def term(self, record: StepRecord) -> float:
        gap = record.lead.true_distance
        return float(record.ego.speed) if math.isfinite(gap) and gap < self.distance else 0.0


@register_rule
class RSSFollowingDistanceRule(Rule):
    """Simplified RSS: d_min = max(0, (v_e^2 - v_l^2) / (2 a)); the deficit max(0, d_min - d) [m]."""

    name = "rss_deficit"
    description = "minimum following distance deficit (simplified RSS) [m]"
    unit = "m"
    in_total = False
    decel: float = 5.0  # a [m/s^2]
    param_ranges: ClassVar[Mapping[str, ranges.Ranged]] = {"decel": ranges.DECEL}

    def __post_init__(self) -> None:
        _positive(self)

    def term(self, record: StepRecord) -> float:
        gap, v_l = record.lead.true_distance, record.lead.speed
        if not (math.isfinite(gap) and math.isfinite(v_l)):
            return 0.0
        v_e = float(record.ego.speed)
        d_min = max(0.0, (v_e * v_e - v_l * v_l) / (2.0 * self.decel))
        return max(0.0, d_min - gap)


#: Road states on which braking distances at least double (UK Highway Code rule 227): deceleration halves.
WET_ROAD_STATES = frozenset({"wet", "standing_water"})


def stopping_distance_m(speed: float, road_state: str = "dry", reaction_s: float = 0.67,
                        decel: float = 6.5) -> float:
    """Thinking plus braking distance [m] at ``speed`` [m/s]. The defaults are the UK Highway Code's
    typical stopping distances (70 mph: 21 m thinking, 75 m braking: 0.67 s, 6.5 m/s^2); on a wet road
    the braking part doubles."""
    a = decel / 2.0 if road_state in WET_ROAD_STATES else decel
    return speed * reaction_s + speed * speed / (2.0 * a)


def speed_for_visibility(visibility_m: float, road_state: str = "dry", reaction_s: float = 0.67,
                         decel: float = 6.5) -> float:
    """The highest speed [m/s] that stops within ``visibility_m`` (the inverse of ``stopping_distance_m``)."""
    a = decel / 2.0 if road_state in WET_ROAD_STATES else decel
    return a * (-reaction_s + math.sqrt(reaction_s * reaction_s + 2.0 * max(0.0, visibility_m) / a))


@register_rule
class SpeedForVisibilityRule(Rule):
    """Drive at a speed that stops within the distance one can see (UK Highway Code rule 126; German StVO
    section 3(1)): the ego's speed above that speed [m/s], per step. Needs the step's conditions (0 when a
    record has none); reported beside the paper's total, not in it."""

    name = "speed_for_visibility"
    description = "speed above the speed that stops within the visibility [m/s]"
    unit = "m/s"
    in_total = False
    reaction_s: float = 0.67  # [s]
    decel: float = 6.5  # [m/s^2] on a dry road; halved on a wet one
    param_ranges: ClassVar[Mapping[str, ranges.Ranged]] = {"reaction_s": ranges.Ranged(0.01, 10.0, "s"),
                                                           "decel": ranges.DECEL}

    def __post_init__(self) -> None:
        _positive(self)

    def term(self, record: StepRecord) -> float:
        c = record.conditions
        if c is None:
            return 0.0
        limit = speed_for_visibility(c.visibility_m, c.road_state, self.reaction_s, self.decel)
        return max(0.0, float(record.ego.speed) - limit)


@dataclasses.dataclass(frozen=True)
class Rulebook:
    """Rules in priority order (index 0 = highest priority)."""

    rules: tuple[Rule, ...]

    @property
    def names(self) -> list[str]:
        return [r.name for r in self.rules]

    def rule(self, name: str) -> Rule | None:
        return next((r for r in self.rules if r.name == name), None)

    def step_terms(self, record: StepRecord) -> dict[str, float]:
        return {r.name: r.term(record) for r in self.rules}

    def violations(self, records: Sequence[StepRecord]) -> dict[str, float]:
        return {r.name: r.violation(records) for r in self.rules}

    def total(self, violations: Mapping[str, float]) -> float:
        """The episode's total score: the sum of the violations of the rules that count in it."""
        return sum(violations.get(r.name, 0.0) for r in self.rules if r.in_total)

    def metric_columns(self) -> list[str]:
        """The rule columns of results tables, in a stable order: the rules that add into ``total`` (by
        priority), ``total``, then the reported-only rules (the paper's: collision, proximity, total,
        rss_deficit)."""
        counted = [r.name for r in self.rules if r.in_total]
        return [*counted, "total", *(r.name for r in self.rules if not r.in_total)]

    def compare(self, a: Sequence[StepRecord], b: Sequence[StepRecord], tol: float = 1e-9) -> int:
        """-1 if trajectory ``a`` is better (violates less) than ``b``, 1 if worse, 0 if equal: rule by rule
        in priority order, the first difference decides (Censi et al.'s lexicographic order)."""
        for rule in self.rules:
            va, vb = rule.violation(a), rule.violation(b)
            if abs(va - vb) > tol:
                return -1 if va < vb else 1
        return 0

    def describe(self) -> list[dict[str, Any]]:
        """The rulebook as data (records and campaigns store it; ``build_rulebook`` reads it back). A
        plug-in rule also carries its import ``path``; every rule its ``unit`` and ``in_total``."""
        out = []
        for i, r in enumerate(self.rules):
            d: dict[str, Any] = {"priority": i + 1, "name": r.name, "params": r.params()}
            path = r.import_path()
            if path:
                d.update(path=path, unit=r.unit, in_total=r.in_total)
            out.append(d)
        return out


class StoredRule(Rule):
    """A plug-in rule a campaign names but this command may not import (its module is not on the command
    line): its name, unit and parameters as stored, enough to summarise and report the campaign's rows; it
    scores nothing."""

    stored_path: ClassVar[str] = ""

    @classmethod
    def import_path(cls) -> str | None:
        return cls.stored_path

    def term(self, record: StepRecord) -> float:
        raise UserInputError(f"rule '{self.name}' is a plug-in this command did not import; pass --plugin with "
                             "its module to score with it")


def _stored_rule_class(entry: Mapping[str, Any], path: str, where: str) -> type[Rule]:
    unit, in_total, params = entry.get("unit", ""), entry.get("in_total", True), entry.get("params", {})
    if not isinstance(unit, str) or not isinstance(in_total, bool) or not isinstance(params, Mapping):
        raise UserInputError(f"{where}: a stored plug-in rule needs a string unit, a boolean in_total and a "
                             "params table")
    name = str(entry.get("name"))
    fields = [(str(k), float, dataclasses.field(default=0.0)) for k in params]
    cls = dataclasses.make_dataclass(f"Stored_{name}"[:60], fields, bases=(StoredRule,), frozen=True, namespace={
        "name": name, "unit": unit, "in_total": in_total, "stored_path": path,
        "description": f"{name} (plug-in {path}, not imported) [{unit}]"})
    return _as_rule_class(cls, f"{where}: rule '{name}'")


def build_rulebook(entries: Sequence[Mapping[str, Any]], source: str = "rulebook",
                   stored_only: bool = False) -> Rulebook:
    """Rules from ``[{name, priority?, params?, path?}]``; ``name`` is a registered rule or an import path
    ``package.module:Class`` (``path``, as ``describe`` writes it, takes precedence). Sorted by priority
    (1 = highest), else given order; priorities must be distinct. ``stored_only``: a campaign's stored
    rulebook, read to summarise it: a plug-in rule whose module the command may not import becomes a
    :class:`StoredRule` instead of an error."""
    from genesis_rl.core.plugins import import_allowed, module_of

    if not isinstance(entries, list | tuple):
        raise UserInputError(f"{source}: `rules` must be a list of tables ([[rules]]), got {type(entries).__name__}")
    rules: list[tuple[int, int, Rule]] = []
    for i, entry in enumerate(entries):
        where = f"{source}: rules[{i}]"
        if not isinstance(entry, Mapping):
            raise UserInputError(f"{where} must be a table with name, priority, params; got {entry!r}")
        unknown_keys = set(entry) - {"name", "priority", "params", "path", "unit", "in_total"}
        if unknown_keys:
            raise UserInputError(f"{where}: unknown key(s) {sorted(unknown_keys)}; allowed: name, priority, params")
        name = entry.get("name")
        if not isinstance(name, str):
            raise UserInputError(f"{where}: name = {name!r}; allowed: {', '.join(sorted(RULES))} or "
                                 "package.module:Class")
        spec = entry.get("path") or name
        module = module_of(spec) if isinstance(spec, str) and spec not in RULES else None
        if stored_only and module is not None and not import_allowed(module):
            cls = _stored_rule_class(entry, str(spec), where)
        else:
            cls = rule_class(spec, where)
        params = entry.get("params", {})
        if not isinstance(params, Mapping):
            raise UserInputError(f"{where}: params = {params!r} must be a table, e.g. params = {{ distance = 5.0 }}")
        fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        for key, value in params.items():
            if key not in fields:
                allowed = ", ".join(fields) or "(none)"
                raise UserInputError(f"{where}: rule '{cls.name}' has no parameter '{key}'; allowed: {allowed}")
            finite = (isinstance(value, float) and math.isfinite(value)) or \
                (isinstance(value, int) and not isinstance(value, bool) and abs(value) < 2**63)
            if not finite:
                raise UserInputError(f"{where}: {cls.name}.{key} = {value!r} must be a finite number")
        priority = entry.get("priority", i + 1)
        if isinstance(priority, bool) or not isinstance(priority, int) or priority < 1:
            raise UserInputError(f"{where}: priority = {priority!r} must be an integer >= 1")
        try:
            rule = cls(**{k: float(v) for k, v in params.items()})
        except (ValueError, TypeError, OverflowError) as err:
            raise UserInputError(f"{where}: {err}") from None
        for key, value in params.items():  # a physical range (a deceleration of 1e-320 would divide to inf)
            rng = cls.param_ranges.get(key)
            field = f"{where}: {cls.name}.{key}"
            if rng is not None:
                rng.check(value, field)
            else:
                ranges.generic(value, field)
        rules.append((priority, i, rule))
    if not rules:
        raise UserInputError(f"{source}: a rulebook needs at least one rule; allowed: {', '.join(sorted(RULES))}")
    names = [r.name for _, _, r in rules]
    if len(set(names)) != len(names):
        raise UserInputError(f"{source}: a rule appears twice: {names}")
    priorities = [p for p, _, _ in rules]
    if len(set(priorities)) != len(priorities):
        raise UserInputError(f"{source}: two rules share a priority ({priorities}); a rulebook is a strict order: "
                             "give each rule its own priority")
    return Rulebook(tuple(r for _, _, r in sorted(rules, key=lambda t: (t[0], t[1]))))


def default_rulebook() -> Rulebook:
    """The paper's rules: collision before proximity, with the RSS deficit as a third, reported metric."""
    return build_rulebook([{"name": "collision"}, {"name": "proximity"}, {"name": "rss_deficit"}], "default")


def odd_rulebook() -> Rulebook:
    """The paper's rules and speed for visibility: the default rulebook when an ODD is declared."""
    return build_rulebook([{"name": "collision"}, {"name": "proximity"}, {"name": "rss_deficit"},
                           {"name": "speed_for_visibility"}], "default")


def rulebook_for(path: str | Path | None, with_odd: bool) -> Rulebook:
    """An env's rulebook: its file, else the default (with speed for visibility when an ODD is declared)."""
    if path:
        return load_rulebook(path)
    return odd_rulebook() if with_odd else default_rulebook()


def load_rulebook(path: str | Path) -> Rulebook:
    """Read a TOML rulebook: ``[[rules]]`` tables with ``name``, optional ``priority`` and ``params``."""
    from genesis_rl.core.config import read_toml

    data = read_toml(path, "rulebook")
    unknown = set(data) - {"rules"}
    if unknown:
        raise UserInputError(f"rulebook '{path}': unknown key(s) {sorted(unknown)}; allowed: rules")
    return build_rulebook(data.get("rules", []), str(path))


def check_rulebook_imports(path: str | Path, where: str = "env.rulebook") -> None:
    """Hold the import paths a rulebook file names to the command's gate (genesis_rl/core/plugins.py) without
    importing anything: where the envs run elsewhere (Ray actors), the parent refuses them first. A rulebook
    that does not parse is left for the env to report."""
    from genesis_rl.core.config import read_toml
    from genesis_rl.core.plugins import check_import

    try:
        rules = read_toml(path, "rulebook").get("rules", [])
    except UserInputError:
        return
    for rule in rules if isinstance(rules, list) else []:
        name = rule.get("name") if isinstance(rule, dict) else None
        if isinstance(name, str) and ":" in name and name not in RULES:
            check_import(name.partition(":")[0], f"{where} '{path}': rule '{name}'")
