"""Which objective pays for failure: the paper's reward and the falsification objective scored on the same
recorded episodes. An adversary maximises its return; if episodes without a failure can return more than
episodes with one, the return does not point at failures, whatever the optimiser."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from genesis_rl.adversaries.base import in_odd_failure_at
from genesis_rl.campaigns.campaign_files import read_step_records, steps_path
from genesis_rl.campaigns.loaded import load_typed_campaign
from genesis_rl.loop.rules.reward import FalsificationReward, RewardConfig
from genesis_rl.world.step_record import StepRecord


@dataclass(frozen=True)
class ScoredEpisode:
    """One recorded episode's returns under both objectives, and whether it failed inside the ODD."""

    campaign: str
    policy: str
    scene: int
    failed: bool
    paper: float  # the recorded reward, summed over every step (the paper runs on past a collision)
    falsification: float  # the falsification objective, summed up to its first in-ODD failure
    contact: float  # the paper's reward paid on the steps in contact


def falsification_return(records: Sequence[StepRecord], config: RewardConfig | None = None,
                         with_odd: bool = True) -> float:
    """The falsification objective's return of a recorded episode (it ends at the first in-ODD failure)."""
    reward = FalsificationReward(config or RewardConfig(objective="falsification"), episode_steps=len(records),
                                 with_odd=with_odd)
    total = 0.0
    for rec in records:
        total += reward.step_terms(rec, rec.rules)["reward"]
        if reward.is_failure(rec):
            break
    return total


def score_campaign(folder: Path) -> list[ScoredEpisode]:
    """Every episode of the campaign in ``folder``, scored both ways."""
    campaign = load_typed_campaign(folder)
    with_odd = bool(campaign.spec.env.get("odd"))
    out = []
    for policy, rows in campaign.episodes.items():
        for row in rows:
            records = read_step_records(steps_path(folder, policy, row.scene), steps=row.steps)
            out.append(ScoredEpisode(
                f"{folder.parent.name}/{folder.name}", policy, row.scene, in_odd_failure_at(records) is not None,
                sum(float(r.reward["reward"]) for r in records), falsification_return(records, with_odd=with_odd),
                sum(float(r.reward["reward"]) for r in records if r.collision.collided)))
    return out


def separation(episodes: Iterable[ScoredEpisode], objective: str) -> float | None:
    """The chance that a failing episode returns more than one without a failure (ties count half): 1 means the
    return ranks every failure above every non-failure; None without both kinds."""
    episodes = list(episodes)
    failed = [getattr(e, objective) for e in episodes if e.failed]
    passed = [getattr(e, objective) for e in episodes if not e.failed]
    if not failed or not passed:
        return None
    wins = sum((f > p) + 0.5 * (f == p) for f in failed for p in passed)
    return wins / (len(failed) * len(passed))
