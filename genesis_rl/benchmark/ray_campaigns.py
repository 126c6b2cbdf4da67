"""The matrix's campaigns side by side on Ray: each actor runs whole campaigns, one at a time, in a staging
folder of its own, and sends each finished campaign's files back to the driver, which installs them in the
benchmark folder (``benchmark.parallel`` is the same on local processes).

Why: spreading a short campaign's episodes over actors pays the campaign's set-up in every actor and leaves
actors idle while its slowest episode finishes, so Ray's wall time fell little with workers (docs/zoo.md). A
whole campaign per actor scales as the local processes do, and the files travel back as an episode's do on
Ray (``evaluation.executors``), so a cluster needs no shared folder. A half-run campaign (an earlier local
run stopped) travels to its actor and resumes there. A lost actor costs its campaign, which goes back to the
queue and runs again elsewhere (``RayEpisodeScheduler``). Each campaign is the same campaign whoever runs it
(its episodes are seeded by their tasks), so the leaderboard is the same.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.campaigns.executors import RayEpisodeScheduler, folder_files, write_files
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.files.io_utils import atomic_write_text
from genesis_rl.core.signals import deferred_signals
from genesis_rl.distributed.settings import ExecutorSettings

#: a campaign as it travels to an actor: its spec (JSON), its folder on the driver (for messages and the
#: answer), and the files a half-run campaign left there (relative path -> bytes; empty for a new one)
CampaignJob = tuple[dict[str, Any], str, dict[str, bytes]]
#: files the driver writes itself once the campaign is installed (they name the folder, or mark it finished)
DRIVER_WRITES = (CampaignFolder.SUMMARY, CampaignFolder.EPISODES_CSV)


def _describe(job: CampaignJob) -> str:
    return f"the campaign '{job[1]}'"


class CampaignActor:
    """A Ray actor that runs whole campaigns, each in a fresh staging folder, and returns its files."""

    def __init__(self, plugins: tuple[str, ...], paths: list[str]) -> None:
        from genesis_rl.core.plugins import import_modules
        from genesis_rl.distributed.ray_cluster import add_driver_paths

        add_driver_paths(paths)
        import_modules(plugins, checked=False)

    def where(self) -> tuple[str, str]:
        """(node id, node IP): answered once the actor is up, which is when it takes campaigns."""
        from genesis_rl.distributed.ray_cluster import where_am_i

        return where_am_i()

    def run(self, job: CampaignJob) -> tuple[str, dict[str, bytes]]:
        from genesis_rl.benchmark.campaign_once import run_campaign_once

        spec_json, folder, started = job
        stage = Path(tempfile.mkdtemp(prefix="genesis-rl-campaign-"))
        try:
            campaign = stage / "campaign"
            if started:
                write_files(campaign, started)
            run_campaign_once(CampaignSpec.from_json(spec_json), campaign, workers=1)
            files = {rel: data for rel, data in folder_files(campaign).items() if rel not in DRIVER_WRITES}
        finally:
            shutil.rmtree(stage, ignore_errors=True)
        return folder, files

    def close(self) -> None:
        pass


def install(folder: Path, files: dict[str, bytes]) -> None:
    """A finished campaign's files into ``folder``: written beside it, swapped in whole, then summarised there
    (summary.json, which marks the campaign finished, is written last and names ``folder``)."""
    from genesis_rl.campaigns.summary import summarize_campaign

    incoming = folder.with_name(f".{folder.name}.incoming")
    old = folder.with_name(f".{folder.name}.replaced")
    with deferred_signals():  # Ctrl-C does not leave the folder half swapped
        for leftover in (incoming, old):
            shutil.rmtree(leftover, ignore_errors=True)
        write_files(incoming, files)
        if folder.exists():
            os.replace(folder, old)  # a half-run campaign's files, which its actor resumed from
        os.replace(incoming, folder)
        shutil.rmtree(old, ignore_errors=True)
        times = CampaignFolder(folder).run_time
        if times.exists():  # the actor ran it as one local worker; say where it ran
            record = {**json.loads(times.read_text()), "executor": "ray (a campaign per actor)"}
            atomic_write_text(times, json.dumps(record))
        summarize_campaign(folder)


def run_campaigns_on_ray(jobs: Sequence[tuple[CampaignSpec, Path]], settings: ExecutorSettings,
                         on_done: Callable[[Path], None] = lambda folder: None) -> None:
    """Run every campaign of ``jobs`` on ``settings.workers`` Ray actors, a campaign per actor at a time;
    ``on_done`` sees each folder once its campaign is installed (in any order)."""
    from genesis_rl.campaigns.worker import plugin_modules
    from genesis_rl.distributed.ray_cluster import driver_paths, ray_session
    from genesis_rl.distributed.ray_head import HeadWatch

    n = min(settings.workers, len(jobs))
    if n == 0:
        return
    tasks: list[CampaignJob] = [(spec.to_json(), str(folder), folder_files(folder)) for spec, folder in jobs]
    with ray_session(settings.ray_address, n, settings.ray_resources(0)) as ray:
        remote = ray.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(CampaignActor)
        plugins_ref, paths_ref = ray.put(tuple(plugin_modules())), ray.put(driver_paths())

        def make(i: int) -> Any:
            return remote.options(resources=settings.ray_resources(i)).remote(plugins_ref, paths_ref)

        scheduler = RayEpisodeScheduler(ray, make, n, tasks, max_losses=2, describe=_describe, unit="campaign",
                                        watch=HeadWatch.of(ray, settings.ray_address))
        try:
            for folder, files in scheduler.run():
                install(Path(folder), files)
                on_done(Path(folder))
        finally:
            scheduler.close()
