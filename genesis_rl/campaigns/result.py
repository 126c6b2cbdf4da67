"""What a finished campaign run returns, typed: ``summary.json``'s content plus how the run went.

:class:`CampaignResult` and :class:`PolicySummary` name the fields the commands read (each policy's episodes,
collisions and failure modes, the run's seconds, workers and executor) and keep everything else as written.
Both are also read-only mappings of every field, so code written against the summary dictionary reads them
unchanged, and they compare equal to the ``summary.json`` they were made from.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.fields_mapping import FieldsMapping


@dataclass(frozen=True)
class MeanInterval:
    """A metric's mean over the episodes with its bootstrap interval (None: no episode had a value)."""

    n: int
    mean: float | None
    ci_low: float | None
    ci_high: float | None

    @classmethod
    def from_json(cls, value: Mapping[str, Any]) -> MeanInterval:
        return cls(int(value.get("n", 0)), value.get("mean"), value.get("ci_low"), value.get("ci_high"))


@dataclass(frozen=True, eq=False)  # eq=False: compared as a mapping, so equal to the dict it was made from
class PolicySummary(FieldsMapping):
    """One policy's entry in ``summary.json``: how many episodes, how many collided, and how they failed."""

    policy: str
    episodes: int
    missing: int
    episodes_with_collision: int
    collision_events: int
    failure_modes: Mapping[str, int]
    sim_steps: int
    fields: Mapping[str, Any] = field(repr=False)

    @classmethod
    def from_json(cls, policy: str, stats: Mapping[str, Any]) -> PolicySummary:
        return cls(policy=policy, episodes=int(stats["episodes"]), missing=int(stats["missing"]),
                   episodes_with_collision=int(stats["episodes_with_collision"]),
                   collision_events=int(stats["collision_events"]),
                   failure_modes=MappingProxyType(dict(stats["failure_modes"])), sim_steps=int(stats["sim_steps"]),
                   fields=MappingProxyType(copy.deepcopy(dict(stats))))

    def metric(self, name: str) -> MeanInterval:
        """A rule metric's (or ``total``'s, or ``return``'s) mean and interval; KeyError names an unknown one."""
        value = self.fields[name]
        if not (isinstance(value, Mapping) and "mean" in value):
            raise KeyError(f"'{name}' is not a metric of policy '{self.policy}'")
        return MeanInterval.from_json(value)


@dataclass(frozen=True, eq=False)
class CampaignResult(FieldsMapping):
    """What ``run_campaign`` returns: the summary it wrote to ``summary.json`` and the run's own figures (its
    seconds, workers and executor, which summary.json leaves out so that it is the same however it ran)."""

    folder: CampaignFolder
    complete: bool
    scenes: int
    steps: int
    map: str
    seed: int
    policies: Mapping[str, PolicySummary]
    run_seconds: float
    workers: int
    executor: str
    fields: Mapping[str, Any] = field(repr=False)

    @classmethod
    def from_summary(cls, summary: Mapping[str, Any], run_seconds: float, workers: int,
                     executor: str) -> CampaignResult:
        """The result of a run whose ``summarize_campaign`` gave ``summary``."""
        policies = {p: PolicySummary.from_json(p, s) for p, s in summary["policies"].items()}
        fields = {**copy.deepcopy(dict(summary)), "run_seconds": run_seconds, "workers": workers,
                  "executor": executor}
        return cls(folder=CampaignFolder(Path(summary["campaign"])), complete=bool(summary["complete"]),
                   scenes=int(summary["scenes"]), steps=int(summary["steps"]), map=str(summary["map"]),
                   seed=int(summary["seed"]), policies=MappingProxyType(policies), run_seconds=run_seconds,
                   workers=workers, executor=executor, fields=MappingProxyType(fields))

    def to_json(self) -> dict[str, Any]:
        """A plain copy of every field (what ``json.dumps`` takes)."""
        return copy.deepcopy(dict(self.fields))

    def __getitem__(self, key: str) -> Any:
        return self.policies if key == "policies" else self.fields[key]
