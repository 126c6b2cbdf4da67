"""The matrix's campaigns side by side: ``workers`` spawned processes, each running whole campaigns one episode
at a time, instead of each campaign spreading its episodes over the workers.

Why: a campaign's set-up (its catalog, a renderer and a detector in every worker) is paid again for each
campaign, and a campaign's last episodes leave workers idle while the slowest finishes. With many short
campaigns (a benchmark's members x trials) that bound the episode-level scaling to 1.3-1.65x on 2 workers
(docs/zoo.md). Each campaign is still the same campaign (its episodes are seeded by their tasks), so the
leaderboard is the same either way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.distributed.spawn_pool import SpawnPool

#: a campaign job: its spec (as JSON, which pickles plainly) and its folder
Job = tuple[dict[str, Any], str]


def _init(plugins: Sequence[str]) -> None:
    """Import the plug-ins the parent had imported, through its gate (a failure reaches the parent through
    the process's first campaign: SpawnPool)."""
    from genesis_rl.core.plugins import import_modules

    import_modules(plugins, checked=False)


def _run(job: Job) -> str:
    from genesis_rl.benchmark.campaign_once import run_campaign_once

    spec_json, folder = job
    run_campaign_once(CampaignSpec.from_json(spec_json), Path(folder), workers=1)
    return folder


def run_side_by_side(jobs: Sequence[tuple[CampaignSpec, Path]], workers: int,
                     on_done: Callable[[Path], None] = lambda folder: None) -> None:
    """Run every campaign of ``jobs`` on ``workers`` processes, each campaign in one process; ``on_done`` sees
    each folder as its campaign finishes (in any order)."""
    from genesis_rl.campaigns.worker import plugin_modules

    payload = [(spec.to_json(), str(folder)) for spec, folder in jobs]
    pool = SpawnPool(min(workers, len(payload)), _init, (tuple(plugin_modules()),))
    try:
        for folder in pool.imap_unordered(_run, payload):
            on_done(Path(folder))
    except BaseException:
        pool.terminate()  # Ctrl-C or a campaign's error: the rest stop; a half-run campaign resumes
        raise
    pool.close()
