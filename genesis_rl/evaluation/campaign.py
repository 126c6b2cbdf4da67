"""Evaluation campaigns: every policy drives the same held-out scenes with the same episode seeds.

The campaign is split by job: ``campaign_spec`` (what it is, checked up front), ``campaign_folder`` (creating
and resuming its folder), ``episodes`` (one episode and its files), ``campaign_files`` (reading the folder
back) and this module, the runner: episodes run in worker processes (spawned; each re-imports the user
modules that registered plug-ins), each writes its own files and, last, its summary row, so an interrupted
campaign resumes (``--resume``) without redoing finished episodes, and gives the same results whatever the
number of workers.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import shutil
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from genesis_rl import output_folder
from genesis_rl.errors import SimulatorLost, UserInputError
from genesis_rl.evaluation.campaign_folder import Task, prepare_campaign
from genesis_rl.evaluation.campaign_spec import CampaignSpec, env_settings_for, pick_scenes, run_folder_of
from genesis_rl.evaluation.episodes import CampaignRunner, episode_row, write_episode
from genesis_rl.evaluation.failure_modes import FAILURE_MODES, FailureModeThresholds
from genesis_rl.evaluation.policies import POLICIES, PolicyContext, WeatherPolicy, resolve_policy
from genesis_rl.evaluation.summary import summarize_campaign
from genesis_rl.io_utils import atomic_write_text
from genesis_rl.knobs import KNOB_MODULES
from genesis_rl.plugins import import_modules, user_modules
from genesis_rl.rules.rulebook import RULES

# -- one episode, in a worker ---------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def plugin_modules() -> list[str]:
    """The user modules that registered a policy, a rule or a knob in this process (``@register_policy``,
    ``@register_rule``, ``register_knob``): spawned workers import them again, so the names resolve there."""
    return user_modules([*POLICIES.values(), *RULES.values()], KNOB_MODULES.values())


def _worker_init(spec_json: dict[str, Any], folder: str, torch_threads: int, plugins: Sequence[str] = ()) -> None:
    import_modules(plugins)
    torch.set_num_threads(torch_threads)
    spec_json = dict(spec_json)
    spec_json["policies"] = tuple(spec_json["policies"])
    _WORKER.clear()
    _WORKER.update(spec=CampaignSpec(**spec_json), folder=Path(folder), runner=None, policies={})


def _policy(name: str) -> WeatherPolicy:
    spec: CampaignSpec = _WORKER["spec"]
    if name not in _WORKER["policies"]:
        runner: CampaignRunner = _WORKER["runner"]
        ctx = PolicyContext(action_dim=runner.env.mapper.action_dim, seed=spec.seed,
                            agent_path=Path(spec.agent) if spec.agent else None,
                            options={**spec.options, "steps": spec.steps})
        _WORKER["policies"][name] = resolve_policy(name)(ctx)
    return _WORKER["policies"][name]


def run_task(task: tuple[str, int, int]) -> dict[str, Any]:
    """Play one (policy, scene, episode seed) and write its files; returns its summary row."""
    policy_name, scene, episode_seed = task
    spec: CampaignSpec = _WORKER["spec"]
    folder: Path = _WORKER["folder"]
    if _WORKER["runner"] is None:
        _WORKER["runner"] = CampaignRunner(spec, folder)
    runner: CampaignRunner = _WORKER["runner"]
    retries = int(spec.options.get("retries", 2))
    t0 = time.perf_counter()
    for attempt in range(retries + 1):
        try:
            outcome = _policy(policy_name).run_episode(runner, scene, episode_seed)
            break
        except SimulatorLost as err:  # nothing of this episode was written yet: reconnect and run it again
            if attempt == retries:
                raise
            warnings.warn(f"{policy_name} scene {scene}: simulator lost ({err}); reconnecting, retry "
                          f"{attempt + 1} of {retries}", stacklevel=1)
            try:
                runner.close()
            except Exception:  # noqa: BLE001 - the old connection is gone anyway
                pass
            runner = _WORKER["runner"] = CampaignRunner(spec, folder)
    seconds = time.perf_counter() - t0
    return write_episode(folder, spec, runner, policy_name, scene, episode_seed, outcome, seconds)


def run_campaign(spec: CampaignSpec, folder: Path, workers: int = 1, force: bool = False, resume: bool = False,
                 progress: bool = True) -> dict[str, Any]:
    """Run every (policy, scene) not yet done, then write summary.json; returns the summary. The folder is
    held for the whole run: a second campaign into it is refused, not mixed in."""
    with output_folder.hold(folder):
        return _run_campaign(spec, folder, workers, force, resume, progress)


def _run_campaign(spec: CampaignSpec, folder: Path, workers: int, force: bool, resume: bool,
                  progress: bool) -> dict[str, Any]:
    if workers < 1:
        raise UserInputError(f"--workers = {workers} must be >= 1")
    tasks = prepare_campaign(spec, folder, force, resume, progress)  # checks policies and agent first
    t0 = time.perf_counter()
    init_args = (spec.to_json(), str(folder), 1, plugin_modules())
    bar = tqdm(total=len(tasks), desc="evaluate", unit="episode", disable=not progress)
    try:
        if workers == 1 or len(tasks) <= 1:
            _worker_init(*init_args)
            try:
                for task in tasks:
                    row = run_task(task)
                    bar.set_postfix_str(f"{row['policy']} scene {row['scene']} coll={row['collision_events']}")
                    bar.update()
            finally:
                if _WORKER.get("runner") is not None:
                    _WORKER["runner"].close()
        else:
            ctx = mp.get_context("spawn")
            # longest tasks first (search baselines) so workers finish together; stable for equal costs
            tasks.sort(key=lambda t: -resolve_policy(t[0]).episodes_per_scene(spec.options))
            with ctx.Pool(min(workers, len(tasks)), initializer=_worker_init, initargs=init_args) as pool:
                for row in pool.imap_unordered(run_task, tasks):
                    bar.set_postfix_str(f"{row['policy']} scene {row['scene']} coll={row['collision_events']}")
                    bar.update()
    except BaseException:
        if not resume and not any((folder / "episodes").glob("*/*.json")):
            # no episode finished (e.g. the agent's env settings are invalid): leave no folder behind that a
            # corrected re-run would need --force to replace
            shutil.rmtree(folder, ignore_errors=True)
        raise
    finally:
        bar.close()
    summary = summarize_campaign(folder)
    summary["run_seconds"] = round(time.perf_counter() - t0, 1)
    summary["workers"] = workers
    atomic_write_text(folder / "run_time.json", json.dumps({"seconds": summary["run_seconds"], "workers": workers,
                                                           "episodes_run": len(tasks), "cpus": os.cpu_count()}))
    return summary




__all__ = ["CampaignSpec", "CampaignRunner", "FAILURE_MODES", "FailureModeThresholds", "pick_scenes",
           "prepare_campaign", "run_campaign", "env_settings_for", "run_folder_of", "episode_row", "Task"]
