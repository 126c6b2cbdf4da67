"""Where a campaign's episodes run: ``local`` (this process, or a pool of spawned processes on this machine)
or ``ray`` (Ray actors on a local Ray instance or on a cluster).

Every executor runs :func:`worker.run_task` on the same (policy, scene, episode seed) tasks, so the results
are the same whatever the executor and the number of workers. A Ray actor writes an episode into a staging
folder of its own and sends the files back with its summary row; the driver writes them into the campaign
folder, the row last (it marks the episode done), so a cluster needs no shared filesystem for results and a
resumed campaign reads the same folder whichever executor wrote it. An actor that dies (a node lost, a
worker killed) is restarted by Ray and its episode run again: nothing of that episode was written yet.
"""

from __future__ import annotations

import multiprocessing as mp
import shutil
import signal
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from genesis_rl.distributed.settings import ExecutorSettings
from genesis_rl.evaluation.campaign_folder import Task
from genesis_rl.evaluation.worker import close_worker, init_worker, run_task
from genesis_rl.io_utils import atomic_write


@dataclass(frozen=True)
class WorkerSetup:
    """What every worker starts from: the campaign's spec, its folder, the user plug-in modules to import."""

    spec_json: dict[str, Any]
    folder: Path
    plugins: tuple[str, ...]


def run_tasks(tasks: Sequence[Task], setup: WorkerSetup, settings: ExecutorSettings) -> Iterator[dict[str, Any]]:
    """Run ``tasks``; yields each episode's summary row as it finishes (in any order)."""
    if settings.kind == "ray":
        yield from _run_ray(tasks, setup, settings)
    elif settings.workers == 1 or len(tasks) <= 1:
        yield from _run_here(tasks, setup, settings)
    else:
        yield from _run_pool(tasks, setup, settings)


# -- local ----------------------------------------------------------------------------------------------
def _run_here(tasks: Sequence[Task], setup: WorkerSetup, settings: ExecutorSettings) -> Iterator[dict[str, Any]]:
    init_worker(setup.spec_json, str(setup.folder), 1, setup.plugins, settings.server(0))
    try:
        for task in tasks:
            yield run_task(task)
    finally:
        close_worker()


def _pool_init(setup: WorkerSetup, next_slot: Any, servers: list[dict[str, Any]]) -> None:
    """A pool process takes the next worker slot, and with it its CARLA server. Ctrl-C, which a terminal sends
    to every process of the command, is the parent's to handle: it stops the pool (SIGTERM), and a worker
    finishes the file it is writing first (``signals.deferred_signals``), without a traceback of its own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with next_slot.get_lock():
        slot = next_slot.value
        next_slot.value += 1
    init_worker(setup.spec_json, str(setup.folder), 1, setup.plugins, servers[slot])


def _run_pool(tasks: Sequence[Task], setup: WorkerSetup, settings: ExecutorSettings) -> Iterator[dict[str, Any]]:
    ctx = mp.get_context("spawn")
    n = min(settings.workers, len(tasks))
    servers = [settings.server(i) for i in range(n)]
    with ctx.Pool(n, initializer=_pool_init, initargs=(setup, ctx.Value("i", 0), servers)) as pool:
        yield from pool.imap_unordered(run_task, tasks)


# -- Ray ------------------------------------------------------------------------------------------------
class EpisodeActor:
    """A Ray actor: one worker with a staging folder of its own; each episode's files travel back with its
    row (as bytes, by relative path) and leave the staging folder."""

    def __init__(self, setup: WorkerSetup, catalog_json: bytes, env_settings: dict[str, Any],
                 paths: list[str]) -> None:
        from genesis_rl.distributed.ray_cluster import add_driver_paths

        add_driver_paths(paths)
        self.stage = Path(tempfile.mkdtemp(prefix="genesis-rl-episode-"))
        (self.stage / "catalog.json").write_bytes(catalog_json)
        init_worker(setup.spec_json, str(self.stage), 1, setup.plugins, env_settings)

    def run(self, task: Task) -> tuple[dict[str, Any], dict[str, bytes]]:
        row = run_task(task)
        files: dict[str, bytes] = {}
        for path in sorted(self.stage.rglob("*")):
            if path.is_file() and path.name != "catalog.json":
                files[path.relative_to(self.stage).as_posix()] = path.read_bytes()
                path.unlink()
        return row, files

    def close(self) -> None:
        close_worker()
        shutil.rmtree(self.stage, ignore_errors=True)


def _bytes_writer(data: bytes) -> Any:
    return lambda path: path.write_bytes(data)


def write_files(folder: Path, files: dict[str, bytes]) -> None:
    """An episode's files into the campaign folder, atomically each, its row (``episodes/``) last."""
    for rel in sorted(files, key=lambda r: (r.startswith("episodes/"), r)):
        target = folder / rel
        if ".." in Path(rel).parts:
            raise RuntimeError(f"a worker sent a file outside the campaign folder: {rel}")
        atomic_write(target, _bytes_writer(files[rel]))


def _run_ray(tasks: Sequence[Task], setup: WorkerSetup, settings: ExecutorSettings) -> Iterator[dict[str, Any]]:
    from ray.util import ActorPool

    from genesis_rl.distributed.ray_cluster import driver_paths, ray_session

    retries = int(setup.spec_json.get("options", {}).get("retries", 2))
    n = min(settings.workers, len(tasks))
    if n == 0:
        return
    with ray_session(settings.ray_address, n, settings.ray_resources(0)) as ray:
        remote = ray.remote(num_cpus=1, max_restarts=retries + 1, max_task_retries=retries + 1)(EpisodeActor)
        # put once and held here for the whole campaign: a restarted actor is built from the same objects (Ray
        # drops inlined constructor arguments from its store, and the restart would fail)
        setup_ref = ray.put(setup)
        catalog_ref = ray.put((setup.folder / "catalog.json").read_bytes())
        paths_ref = ray.put(driver_paths())
        actors = [remote.options(resources=settings.ray_resources(i)).remote(
            setup_ref, catalog_ref, settings.server(i), paths_ref) for i in range(n)]
        try:
            pool = ActorPool(actors)
            for row, files in pool.map_unordered(lambda a, t: a.run.remote(t), list(tasks)):
                write_files(setup.folder, files)
                yield row
        finally:
            for a in actors:
                try:
                    ray.get(a.close.remote(), timeout=30)
                except Exception:  # noqa: BLE001 - a dead actor has nothing left to close
                    pass
