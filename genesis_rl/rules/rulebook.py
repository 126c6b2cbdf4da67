"""Rules and rulebooks in the formalism of Censi et al. (2019), "Liability, ethics and culture-aware
behavior specification using rulebooks".

A rule maps a trajectory (the step records so far) to a violation >= 0 (0 = compliant), as a sum of
per-step terms, so that the violation can be read step by step (for the reward) and as a whole (for
evaluation). A rulebook is a set of rules with a priority order: two trajectories compare rule by rule,
highest priority first, and the first rule on which they differ decides.

Adding a rule is one small class::

    @register_rule
    class Speeding(Rule):
        name = "speeding"
        limit: float = 13.9  # parameters are dataclass fields with defaults

        def term(self, record):
            return max(0.0, record["ego_speed"] - self.limit)

Rulebooks are declared in TOML (see ``configs/rulebook.toml``); an unknown rule or parameter fails when
the file is loaded.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

from genesis_rl.errors import UserInputError

RULES: dict[str, type[Rule]] = {}


def register_rule(cls: type[Rule]) -> type[Rule]:
    """Class decorator: make a rule available to rulebooks by its ``name``."""
    dataclasses.dataclass(frozen=True)(cls)
    RULES[cls.name] = cls
    return cls


class Rule:
    """A rule: ``term(record)`` is one step's contribution (>= 0); the violation is their sum."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""

    def term(self, record: Mapping[str, Any]) -> float:
        raise NotImplementedError

    def violation(self, records: Sequence[Mapping[str, Any]]) -> float:
        return float(sum(self.term(r) for r in records))

    def params(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]


def _finite(v: Any) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


@register_rule
class CollisionRule(Rule):
    """a_c: the ego's speed [m/s] at a step where it collides (the paper's collision rule)."""

    name = "collision"
    description = "ego speed at each step with a collision [m/s]"

    def term(self, record: Mapping[str, Any]) -> float:
        return float(record["collision_speed"]) if record["collision"] else 0.0


@register_rule
class ProximityRule(Rule):
    """a_p: the ego's speed [m/s] while the gap to its lead is under ``distance`` metres."""

    name = "proximity"
    description = "ego speed while the gap to the lead vehicle is under the threshold [m/s]"
    distance: float = 5.0

    def term(self, record: Mapping[str, Any]) -> float:
        gap = _finite(record["true_lead_distance"])
        return float(record["ego_speed"]) if gap is not None and gap < self.distance else 0.0


@register_rule
class RSSFollowingDistanceRule(Rule):
    """Simplified RSS: d_min = max(0, (v_e^2 - v_l^2) / (2 a)); the deficit max(0, d_min - d) [m]."""

    name = "rss_deficit"
    description = "minimum following distance deficit (simplified RSS) [m]"
    decel: float = 5.0

    def term(self, record: Mapping[str, Any]) -> float:
        gap = _finite(record["true_lead_distance"])
        v_l = _finite(record["lead_speed"])
        if gap is None or v_l is None:
            return 0.0
        v_e = float(record["ego_speed"])
        d_min = max(0.0, (v_e * v_e - v_l * v_l) / (2.0 * self.decel))
        return max(0.0, d_min - gap)


@dataclasses.dataclass(frozen=True)
class Rulebook:
    """Rules in priority order (index 0 = highest priority)."""

    rules: tuple[Rule, ...]

    @property
    def names(self) -> list[str]:
        return [r.name for r in self.rules]

    def step_terms(self, record: Mapping[str, Any]) -> dict[str, float]:
        return {r.name: r.term(record) for r in self.rules}

    def violations(self, records: Sequence[Mapping[str, Any]]) -> dict[str, float]:
        return {r.name: r.violation(records) for r in self.rules}

    def compare(self, a: Sequence[Mapping[str, Any]], b: Sequence[Mapping[str, Any]], tol: float = 1e-9) -> int:
        """-1 if trajectory ``a`` is better (violates less) than ``b``, 1 if worse, 0 if equal: rule by rule
        in priority order, the first difference decides (Censi et al.'s lexicographic order)."""
        for rule in self.rules:
            va, vb = rule.violation(a), rule.violation(b)
            if abs(va - vb) > tol:
                return -1 if va < vb else 1
        return 0

    def describe(self) -> list[dict[str, Any]]:
        return [{"priority": i + 1, "name": r.name, "params": r.params()} for i, r in enumerate(self.rules)]


def build_rulebook(entries: Sequence[Mapping[str, Any]], source: str = "rulebook") -> Rulebook:
    """Rules from ``[{name, priority?, params?}]``; sorted by priority (1 = highest), else given order."""
    rules: list[tuple[float, int, Rule]] = []
    for i, entry in enumerate(entries):
        where = f"{source}: rules[{i}]"
        unknown_keys = set(entry) - {"name", "priority", "params"}
        if unknown_keys:
            raise UserInputError(f"{where}: unknown key(s) {sorted(unknown_keys)}; allowed: name, priority, params")
        name = entry.get("name")
        if name not in RULES:
            raise UserInputError(f"{where}: unknown rule '{name}'; allowed: {', '.join(sorted(RULES))}")
        cls = RULES[name]
        params = dict(entry.get("params", {}))
        fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        for key, value in params.items():
            if key not in fields:
                allowed = ", ".join(fields) or "(none)"
                raise UserInputError(f"{where}: rule '{name}' has no parameter '{key}'; allowed: {allowed}")
            if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
                raise UserInputError(f"{where}: {name}.{key} = {value!r} must be a positive number")
        priority = entry.get("priority", i + 1)
        if not isinstance(priority, int) or priority < 1:
            raise UserInputError(f"{where}: priority = {priority!r} must be an integer >= 1")
        rules.append((priority, i, cls(**{k: float(v) for k, v in params.items()})))
    if not rules:
        raise UserInputError(f"{source}: a rulebook needs at least one rule; allowed: {', '.join(sorted(RULES))}")
    names = [r.name for _, _, r in rules]
    if len(set(names)) != len(names):
        raise UserInputError(f"{source}: a rule appears twice: {names}")
    return Rulebook(tuple(r for _, _, r in sorted(rules, key=lambda t: (t[0], t[1]))))


def default_rulebook() -> Rulebook:
    """The paper's rules: collision before proximity, with the RSS deficit as a third, reported metric."""
    return build_rulebook([{"name": "collision"}, {"name": "proximity"}, {"name": "rss_deficit"}], "default")


def load_rulebook(path: str | Path) -> Rulebook:
    """Read a TOML rulebook: ``[[rules]]`` tables with ``name``, optional ``priority`` and ``params``."""
    path = Path(path)
    if not path.is_file():
        raise UserInputError(f"rulebook file '{path}' does not exist")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as err:
        raise UserInputError(f"rulebook '{path}' is not valid TOML: {err}") from None
    unknown = set(data) - {"rules"}
    if unknown:
        raise UserInputError(f"rulebook '{path}': unknown key(s) {sorted(unknown)}; allowed: rules")
    return build_rulebook(data.get("rules", []), str(path))
