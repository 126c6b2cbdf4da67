"""Evaluation campaigns: every policy drives the same held-out scenes with the same episode seeds.

The campaign is split by job: ``campaign_spec`` (what it is, checked up front), ``campaign_folder`` (creating
and resuming its folder), ``episodes`` (one episode and its files), ``campaign_files`` (reading the folder
back), ``worker`` (one episode in a worker), ``executors`` (where workers run: this process, a local process
pool or Ray actors) and this module, the runner. Each episode's files are written with its summary row last,
so an interrupted campaign resumes (``--resume``) without redoing finished episodes, and gives the same
results whatever the executor and the number of workers.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from tqdm import tqdm

from genesis_rl.adversaries import resolve_policy
from genesis_rl.campaigns.campaign_folder import Task, prepare_campaign
from genesis_rl.campaigns.campaign_spec import CampaignSpec, env_settings_for, pick_scenes, run_folder_of
from genesis_rl.campaigns.episodes import CampaignRunner, episode_row
from genesis_rl.campaigns.executors import WorkerSetup, run_tasks
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.campaigns.result import CampaignResult
from genesis_rl.campaigns.summary import summarize_campaign
from genesis_rl.campaigns.worker import plugin_modules
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write_text
from genesis_rl.core.signals import deferred_signals, set_resume_hint
from genesis_rl.distributed.ray_cluster import RayWorkersLost
from genesis_rl.distributed.settings import ExecutorSettings
from genesis_rl.labels.failure_modes import FAILURE_MODES, FailureModeThresholds


def run_campaign(spec: CampaignSpec, folder: Path, workers: int = 1, force: bool = False, resume: bool = False,
                 progress: bool = True, executor: ExecutorSettings | None = None) -> CampaignResult:
    """Run every (policy, scene) not yet done, then write summary.json; returns the summary, typed. The folder is
    held for the whole run: a second campaign into it is refused, not mixed in. ``executor`` says where the
    episodes run (default: ``workers`` local processes)."""
    settings = executor or ExecutorSettings(workers=workers)
    settings.preflight()  # before the folder is touched: a bad --ray-address writes nothing
    with output_folder.hold(folder):
        return _run_campaign(spec, folder, settings, force, resume, progress)


def _run_campaign(spec: CampaignSpec, folder: Path, settings: ExecutorSettings, force: bool, resume: bool,
                  progress: bool) -> CampaignResult:
    tasks = prepare_campaign(spec, folder, force, resume, progress)  # checks policies and agent first
    t0 = time.perf_counter()
    # longest tasks first (search baselines) so workers finish together; stable for equal costs
    tasks.sort(key=lambda t: -resolve_policy(t[0]).episodes_per_scene(spec.options))
    setup = WorkerSetup(spec.to_json(), folder, tuple(plugin_modules()))
    bar = tqdm(total=len(tasks), desc="evaluate", unit="episode", disable=not progress)
    try:
        for row in run_tasks(tasks, setup, settings):
            bar.set_postfix_str(f"{row['policy']} scene {row['scene']} coll={row['collision_events']}")
            bar.update()
    except BaseException as err:
        done = sum(1 for _ in CampaignFolder(folder).episodes_dir.glob("*/*.json"))
        if not resume and not done:
            # no episode finished (e.g. the agent's env settings are invalid): leave no folder behind that a
            # corrected re-run would need --force to replace
            with deferred_signals():  # a second signal does not leave half a folder
                shutil.rmtree(folder, ignore_errors=True)
            if isinstance(err, KeyboardInterrupt):
                set_resume_hint(err, f"no episode had finished, so '{folder}' was removed; run the command again")
            elif isinstance(err, RayWorkersLost):  # its --resume would be refused: there is nothing to resume
                raise type(err)(f"{err.reason}; no episode had finished, so '{folder}' was removed: run the "
                                "command again", err.reason) from None
        elif isinstance(err, KeyboardInterrupt):
            set_resume_hint(err, f"{done} episode(s) in '{folder}' are kept; the same command with --resume "
                                 "runs the rest")
        raise
    finally:
        bar.close()
    summary = summarize_campaign(folder)
    seconds = round(time.perf_counter() - t0, 1)
    result = CampaignResult.from_summary(summary, seconds, settings.workers, settings.kind)
    atomic_write_text(CampaignFolder(folder).run_time, json.dumps({"seconds": seconds, "workers": settings.workers,
                                                                   "executor": settings.kind,
                                                                   "episodes_run": len(tasks),
                                                                   "cpus": os.cpu_count()}))
    return result




__all__ = ["CampaignResult", "CampaignSpec", "CampaignRunner", "ExecutorSettings", "plugin_modules", "FAILURE_MODES",
           "FailureModeThresholds", "pick_scenes", "prepare_campaign", "run_campaign", "env_settings_for",
           "run_folder_of", "episode_row", "Task"]
