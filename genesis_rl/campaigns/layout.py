"""Where each file of a campaign folder lives: the one place that names them.

A campaign folder is read and written by the runner, the summary, the report, the exports, the benchmark,
the estimate and harden; each asks a :class:`CampaignFolder` for a path instead of spelling the name.

Layout::

    campaign.json                              the spec, scenes, episode seeds, identity, git commit
    catalog.json                               the test catalog the scenes come from
    episodes/<policy>/scene_NNNN.json          one summary row per episode (written last: marks it done)
    steps/<policy>/scene_NNNN.parquet          every step: the flat columns of StepRecord
    frames/<policy>/scene_NNNN/step_NNNN.jpg   camera frames around the first collision
    records/<policy>_scene_NNNN.json           self-contained edge-case records (replayable)
    summary.json, episodes.csv                 the summary (summary.summarize_campaign)
    run_time.json                              the wall time of the run
    report.html                                the report (analysis.report)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


def episode_name(scene: int) -> str:
    """``scene_NNNN``: an episode's name in every per-episode path."""
    return f"scene_{scene:04d}"


@dataclass(frozen=True)
class CampaignFolder:
    """The paths of one campaign folder's files (nothing is read or written here)."""

    root: Path

    META = "campaign.json"
    CATALOG = "catalog.json"
    SUMMARY = "summary.json"
    EPISODES_CSV = "episodes.csv"
    RUN_TIME = "run_time.json"
    REPORT = "report.html"
    EPISODES = "episodes"
    STEPS = "steps"
    FRAMES = "frames"
    RECORDS = "records"

    def __init__(self, root: str | Path) -> None:
        object.__setattr__(self, "root", Path(root))

    @classmethod
    def holds_results(cls, rel: str) -> bool:
        """Whether the file at ``rel`` (inside a campaign folder) is one the episodes wrote, as opposed to what
        ``report`` and the summary rewrite from them: the files a resume that keeps a finished campaign pins."""
        head, sep, _ = rel.partition("/")
        return rel in (cls.META, cls.CATALOG) or bool(sep) and head in (cls.EPISODES, cls.STEPS, cls.FRAMES,
                                                                          cls.RECORDS)

    @property
    def meta(self) -> Path:
        return self.root / self.META

    @property
    def catalog(self) -> Path:
        return self.root / self.CATALOG

    @property
    def summary(self) -> Path:
        return self.root / self.SUMMARY

    @property
    def episodes_csv(self) -> Path:
        return self.root / self.EPISODES_CSV

    @property
    def run_time(self) -> Path:
        return self.root / self.RUN_TIME

    @property
    def report(self) -> Path:
        return self.root / self.REPORT

    @property
    def episodes_dir(self) -> Path:
        return self.root / self.EPISODES

    @property
    def records_dir(self) -> Path:
        return self.root / self.RECORDS

    @property
    def frames_dir(self) -> Path:
        return self.root / self.FRAMES

    def episode(self, policy: str, scene: int) -> Path:
        return self.policy_episodes(policy) / f"{episode_name(scene)}.json"

    def policy_episodes(self, policy: str) -> Path:
        return self.episodes_dir / policy

    def steps(self, policy: str, scene: int) -> Path:
        return self.root / self.STEPS / policy / f"{episode_name(scene)}.parquet"

    def frames(self, policy: str, scene: int) -> Path:
        """The folder of an episode's kept frames (``step_NNNN.jpg``)."""
        return self.root / self.FRAMES / policy / episode_name(scene)

    def record(self, policy: str, scene: int) -> Path:
        return self.root / self.RECORDS / f"{policy}_{episode_name(scene)}.json"

    def is_started(self) -> bool:
        return self.meta.exists()

    def is_finished(self) -> bool:
        """Both the spec and the summary are there (the summary is written last)."""
        return self.meta.exists() and self.summary.exists()
