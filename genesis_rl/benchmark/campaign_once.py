"""One campaign of the benchmark's matrix (or of a zoo sweep), run to its end once: a module of its own so that
the matrix and the processes that run its campaigns side by side (``benchmark.parallel``) both use it without
importing each other."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.campaigns.layout import CampaignFolder


def finished(folder: Path) -> bool:
    """Whether the campaign in ``folder`` ran to its end (its spec and its summary are written)."""
    return CampaignFolder(folder).is_finished()


def run_campaign_once(campaign: CampaignSpec, folder: Path, *, workers: int = 1, executor: Any = None) -> None:
    """Run ``campaign`` into ``folder`` unless it finished there: a half-run one resumes from its finished
    episodes, and a folder left before the campaign wrote its spec (ours) starts again. The benchmark's trials
    and the zoo sweep's values are each one such campaign."""
    from genesis_rl.campaigns.campaign import run_campaign
    from genesis_rl.campaigns.campaign_folder import check_finished_campaign

    started = CampaignFolder(folder).is_started()
    if finished(folder):
        check_finished_campaign(campaign, folder)
        return
    if folder.exists() and not started:
        shutil.rmtree(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    run_campaign(campaign, folder, workers=workers, resume=started, progress=False, executor=executor)
