"""One campaign worker: its environment, its policies, and one episode at a time.

A worker is this process (``--workers 1``), a spawned pool process or a Ray actor
(``evaluation.executors``); each calls :func:`init_worker` once and :func:`run_task` per episode. A task is
(policy, scene, episode seed) and nothing else, so which worker runs it changes nothing in its result.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from genesis_rl.adversaries import POLICIES, WeatherPolicy, resolve_policy
from genesis_rl.adversaries.replay import build_policy
from genesis_rl.campaigns.campaign_folder import Task
from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.campaigns.episodes import CampaignRunner, write_episode
from genesis_rl.core.errors import SimulatorLost
from genesis_rl.core.plugins import import_modules, user_modules
from genesis_rl.loop.rules.rulebook import RULES
from genesis_rl.world.knobs import KNOB_MODULES

_WORKER: dict[str, Any] = {}


def plugin_modules() -> list[str]:
    """The user modules that registered a policy, a rule or a knob in this process (``@register_policy``,
    ``@register_rule``, ``register_knob``): spawned workers import them again, so the names resolve there."""
    return user_modules([*POLICIES.values(), *RULES.values()], KNOB_MODULES.values())


def init_worker(spec_json: dict[str, Any], folder: str, torch_threads: int, plugins: Sequence[str] = (),
                env_settings: dict[str, Any] | None = None) -> None:
    """Set this process up as a worker writing into ``folder``; ``env_settings`` are its own env keys (its
    CARLA server)."""
    import_modules(plugins, checked=False)  # what the parent imported, through its gate
    torch.set_num_threads(torch_threads)
    _WORKER.clear()
    _WORKER.update(spec=CampaignSpec.from_json(spec_json), folder=Path(folder), runner=None, policies={},
                   env_settings=dict(env_settings or {}))


def close_worker() -> None:
    if _WORKER.get("runner") is not None:
        _WORKER["runner"].close()
        _WORKER["runner"] = None


def _runner() -> CampaignRunner:
    if _WORKER["runner"] is None:
        _WORKER["runner"] = CampaignRunner(_WORKER["spec"], _WORKER["folder"], _WORKER["env_settings"])
    return _WORKER["runner"]


def _policy(name: str) -> WeatherPolicy:
    spec: CampaignSpec = _WORKER["spec"]
    if name not in _WORKER["policies"]:
        _WORKER["policies"][name] = build_policy(resolve_policy(name), name,
                                                 spec.policy_context(_runner().env.mapper.action_dim))
    return _WORKER["policies"][name]


def run_task(task: Task) -> dict[str, Any]:
    """Play one (policy, scene, episode seed) and write its files; returns its summary row."""
    policy_name, scene, episode_seed = task
    spec: CampaignSpec = _WORKER["spec"]
    folder: Path = _WORKER["folder"]
    runner = _runner()
    retries = int(spec.options.get("retries", 2))
    t0 = time.perf_counter()
    lost: list[str] = []  # why each earlier attempt was lost: the row says the episode was retried
    for attempt in range(retries + 1):
        try:
            outcome = _policy(policy_name).run_episode(runner, scene, episode_seed)
            break
        except SimulatorLost as err:  # nothing of this episode was written yet: reconnect and run it again
            if attempt == retries:
                raise
            lost.append(str(err))
            warnings.warn(f"{policy_name} scene {scene}: simulator lost ({err}); reconnecting, retry "
                          f"{attempt + 1} of {retries}", stacklevel=1)
            try:
                runner.close()
            except Exception:  # noqa: BLE001 - the old connection is gone anyway
                pass
            _WORKER["runner"] = None
            runner = _runner()
    seconds = time.perf_counter() - t0
    return write_episode(folder, spec, runner, policy_name, scene, episode_seed, outcome, seconds, lost)
