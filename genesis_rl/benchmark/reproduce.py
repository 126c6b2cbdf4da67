"""Re-running reported failures in worlds their adversary never saw: a failure counts when it reproduces.

Lite is deterministic given the scene and the episode's seed, and a search replays its test episode with every
candidate, so a schedule tuned on that episode fails there by construction. Real roads are not replayable. So
every in-ODD failure a policy reports on a benchmark's scene is played again on ``reruns`` fresh *world seeds*
(traffic behaviour, sensor noise and the system's own draws; ``GenesisEnv.reset(world_seed=...)``), drawn from
the benchmark's seed, the member, the trial and the scene, and never shown to any policy:

- a policy that does not react (``WeatherPolicy.reacts`` false: the searches, random, constant) is judged by
  what it reported, its schedule (start and every step's knobs), replayed open loop;
- a policy that reacts (a trained agent, a scripted watcher) plays again, acting on what it sees.

A re-run *reproduces* the failure when it fails inside the ODD too, and on a weakness member when that failure
is triggered (at or after its entering the trigger region). The reproduction is counted per scene; the
leaderboard's primary score needs at least half of the re-runs (``benchmark.metrics``). Files::

    OUT/reproductions/MEMBER/CAMPAIGN.json   per policy and scene: the world seeds, each re-run's failure step
                                             and whether it triggered
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.core.files.io_utils import atomic_write_json
from genesis_rl.sut.zoo.trigger import TriggerRegion

SCHEMA = "genesis-rl/reproductions"
#: re-runs of each reported failure unless the benchmark says otherwise
DEFAULT_RERUNS = 10


def rerun_seeds(seed: int, member: str, trial: int, scene: int, count: int) -> list[int]:
    """The world seeds of one scene's re-runs: fresh for every (benchmark seed, member, trial, scene)."""
    tag = zlib.crc32(member.encode())
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), tag, int(trial), int(scene), 0x2E2]))
    return [int(v) for v in rng.integers(0, 2**31 - 1, count)]


def reproduction_file(out: Path, member: str, campaign: Path) -> Path:
    return Path(out) / "reproductions" / member / f"{Path(campaign).name}.json"


def reproduce_campaign(folder: Path, member: str, region: TriggerRegion, trial: int, seed: int, reruns: int,
                       target: Path) -> dict[str, Any]:
    """Re-run every in-ODD failure the campaign ``folder`` reports on ``member`` (whose trigger region is
    ``region``: passed, not looked up, so that a worker process needs no registry); written to ``target``."""
    from genesis_rl.adversaries import resolve_policy
    from genesis_rl.adversaries.base import in_odd_failure_at
    from genesis_rl.benchmark.metrics import Trial  # local: this module is imported when the parser is built
    from genesis_rl.campaigns.campaign_files import read_step_records
    from genesis_rl.campaigns.episodes import CampaignRunner
    from genesis_rl.campaigns.loaded import load_typed_campaign
    from genesis_rl.campaigns.records import load_record
    from genesis_rl.world.knobs import Weather

    campaign = load_typed_campaign(Path(folder))
    spec = campaign.spec
    runner = CampaignRunner(spec, Path(folder))
    policies: dict[str, dict[str, Any]] = {}
    try:
        for policy, rows in campaign.episodes.items():
            cls = resolve_policy(policy)
            built = None
            per_scene: dict[str, Any] = {}
            for row in rows:
                records = read_step_records(campaign.folder.steps(policy, row.scene), row.steps)
                if in_odd_failure_at(records) is None:
                    continue
                if cls.reacts:
                    if built is None:
                        built = cls(spec.policy_context(runner.env.mapper.action_dim))
                else:  # what it reported: its start and every step's knobs, read once for all the re-runs
                    record = load_record(campaign.folder.root / row.record) if row.record else None
                    start = Weather.from_recorded(record["start_weather"]) if record else None
                    schedule = [Weather.from_recorded(r.knobs) for r in records]
                runs = []
                for world in rerun_seeds(seed, member, trial, row.scene, reruns):
                    runner.in_world(world)
                    played = built.run_episode(runner, row.scene, row.episode_seed).records if built is not None \
                        else runner.replay(row.scene, row.episode_seed, start, schedule)
                    runner.in_world(None)
                    again = Trial(row.scene, len(played), region.reached(played), in_odd_failure_at(played))
                    runs.append({"world_seed": world, "failure_at": again.failure_at,
                                 "reproduced": again.hit(control=region.empty)})
                per_scene[str(row.scene)] = {"reruns": len(runs), "reproduced": sum(r["reproduced"] for r in runs),
                                             "runs": runs}
            policies[policy] = per_scene
    finally:
        runner.close()
    result = {"schema": SCHEMA, "member": member, "campaign": Path(folder).name, "trial": trial, "seed": seed,
              "reruns": reruns, "policies": policies}
    atomic_write_json(target, result, indent=1)
    return result


def load_reproductions(path: Path) -> dict[str, dict[int, tuple[int, int]]]:
    """Per policy and scene: (re-runs, reproduced) from a reproduction file (empty when there is none)."""
    from genesis_rl.core.parsing import read_json

    if not Path(path).is_file():
        return {}
    data = read_json(Path(path), "reproductions")
    return {p: {int(s): (int(v["reruns"]), int(v["reproduced"])) for s, v in scenes.items()}
            for p, scenes in (data.get("policies") or {}).items()}


def run_reproductions(jobs: Sequence[tuple[Path, str, TriggerRegion, int, Path]], seed: int, reruns: int,
                      workers: int, on_done: Callable[[Path], None] | None = None) -> None:
    """Every (campaign folder, member, its trigger region, trial, target) job whose target is missing, ``workers``
    side by side (spawned processes; the results do not depend on which)."""
    todo = [j for j in jobs if not Path(j[4]).is_file()]
    if workers <= 1 or len(todo) <= 1:
        for folder, member, region, trial, target in todo:
            reproduce_campaign(folder, member, region, trial, seed, reruns, target)
            if on_done:
                on_done(target)
        return
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from genesis_rl.core.threads import INFERENCE_THREADS

    with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_threads,
                             initargs=(INFERENCE_THREADS,)) as pool:
        futures = [pool.submit(reproduce_campaign, f, m, r, t, seed, reruns, target) for f, m, r, t, target in todo]
        for fut, job in zip(futures, todo, strict=True):
            fut.result()
            if on_done:
                on_done(job[4])


def _init_threads(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
