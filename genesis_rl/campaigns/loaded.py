"""A finished campaign as typed data: what ``load_campaign``'s nested dictionaries hold, with names and types.

:class:`EpisodeRow` names the fields every stage after the campaign reads (the scene, its seed, the collision,
the failure label, the return) and keeps the rest as written; it is also a read-only mapping of every field,
so code written against the row dictionaries reads it unchanged while new code uses the attributes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.fields_mapping import FieldsMapping


def _frozen(value: Any) -> Mapping[str, Any]:
    return MappingProxyType(dict(value)) if isinstance(value, Mapping) else MappingProxyType({})


@dataclass(frozen=True)
class EpisodeRow(FieldsMapping):
    """One finished episode (``episodes/<policy>/scene_NNNN.json``)."""

    policy: str
    scene: int
    episode_seed: int
    steps: int
    collision_events: int
    first_collision_step: int | None
    failure_mode: str | None
    failure: Mapping[str, Any] | None
    episode_return: float
    record: str | None
    fields: Mapping[str, Any] = field(repr=False)

    @classmethod
    def from_json(cls, row: Mapping[str, Any]) -> EpisodeRow:
        """A row as ``campaign_files.read_episode_row`` checked it."""
        failure = row.get("failure")
        return cls(policy=str(row["policy"]), scene=int(row["scene"]), episode_seed=int(row["episode_seed"]),
                   steps=int(row["steps"]), collision_events=int(row.get("collision_events") or 0),
                   first_collision_step=row.get("first_collision_step"), failure_mode=row.get("failure_mode"),
                   failure=_frozen(failure) if isinstance(failure, Mapping) else None,
                   episode_return=float(row.get("return", 0.0)), record=row.get("record"), fields=_frozen(row))

    @property
    def collided(self) -> bool:
        return self.first_collision_step is not None


@dataclass(frozen=True)
class LoadedCampaign:
    """A campaign folder read whole: its spec, scenes and identity, and every policy's finished episodes."""

    folder: CampaignFolder
    spec: CampaignSpec
    scenes: tuple[tuple[int, int], ...]
    identity: Mapping[str, Any]
    package_version: str | None
    episodes: Mapping[str, tuple[EpisodeRow, ...]]
    meta: Mapping[str, Any] = field(repr=False)

    @property
    def policies(self) -> tuple[str, ...]:
        return self.spec.policies

    def episode_count(self) -> int:
        return sum(len(rows) for rows in self.episodes.values())


def load_typed_campaign(folder: str | Path) -> LoadedCampaign:
    """The campaign in ``folder`` (its rows relabelled where an older labeller wrote them, as ``load_campaign``)."""
    from genesis_rl.campaigns.summary import load_campaign  # local: the summary's imports are heavy

    meta, rows = load_campaign(Path(folder))
    spec_json = dict(meta["spec"])
    known = set(CampaignSpec.__dataclass_fields__)
    spec = CampaignSpec.from_json({k: v for k, v in spec_json.items() if k in known})  # an older file's extras
    return LoadedCampaign(
        folder=CampaignFolder(folder), spec=spec, scenes=tuple((int(s), int(e)) for s, e in meta["scenes"]),
        identity=_frozen(meta.get("identity")), package_version=meta.get("package_version"),
        episodes=MappingProxyType({p: tuple(EpisodeRow.from_json(r) for r in eps) for p, eps in rows.items()}),
        meta=_frozen(meta))
