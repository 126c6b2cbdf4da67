"""Where a campaign's episodes run: ``local`` (this process, or a pool of spawned processes on this machine)
or ``ray`` (Ray actors on a local Ray instance or on a cluster).

Every executor runs :func:`worker.run_task` on the same (policy, scene, episode seed) tasks, so the results
are the same whatever the executor and the number of workers. A Ray actor writes an episode into a staging
folder of its own and sends the files back with its summary row; the driver writes them into the campaign
folder, the row last (it marks the episode done), so a cluster needs no shared filesystem for results and a
resumed campaign reads the same folder whichever executor wrote it.

An actor that is lost (its worker process killed, its node gone) costs only its episode: the episode goes back
to the queue and runs again on the other actors (nothing of it was written yet, and an episode is seeded by its
task, so the re-run is the same episode), a replacement actor is asked for in its place (it starts where the
cluster has room), and one line on stderr names the node and the episodes re-run. The campaign stops, keeping
what it wrote, only when no actor is left and none can be placed within ``REPLACEMENT_WAIT_S``, when one
episode has lost its worker more than ``retries + 1`` times (an episode that kills its worker), or when the
cluster's head stops answering (``distributed/ray_head.py``: Ray would end the process itself 60 s later).
"""

from __future__ import annotations

import multiprocessing as mp
import shutil
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.campaign_folder import Task
from genesis_rl.campaigns.worker import close_worker, init_worker, run_task
from genesis_rl.core.files.io_utils import atomic_write
from genesis_rl.distributed.ray_cluster import RayWorkersLost
from genesis_rl.distributed.ray_head import HeadWatch, RayHeadLost
from genesis_rl.distributed.settings import ExecutorSettings
from genesis_rl.distributed.spawn_pool import SpawnPool


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
    """A pool process takes the next worker slot, and with it its CARLA server. Ctrl-C is the parent's to
    handle (``SpawnPool``): it stops the pool (SIGTERM), and a worker finishes the file it is writing first
    (``signals.deferred_signals``), without a traceback of its own."""
    with next_slot.get_lock():
        slot = next_slot.value
        next_slot.value += 1
    init_worker(setup.spec_json, str(setup.folder), 1, setup.plugins, servers[slot])


def _run_pool(tasks: Sequence[Task], setup: WorkerSetup, settings: ExecutorSettings) -> Iterator[dict[str, Any]]:
    n = min(settings.workers, len(tasks))
    servers = [settings.server(i) for i in range(n)]
    with SpawnPool(n, _pool_init, (setup, mp.get_context("spawn").Value("i", 0), servers)) as pool:
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

    def where(self) -> tuple[str, str]:
        """(node id, node IP): answered once the actor is up, which is when it takes episodes."""
        from genesis_rl.distributed.ray_cluster import where_am_i

        return where_am_i()

    def run(self, task: Task) -> tuple[dict[str, Any], dict[str, bytes]]:
        row = run_task(task)
        files = {rel: data for rel, data in folder_files(self.stage).items() if Path(rel).name != "catalog.json"}
        for rel in files:
            (self.stage / rel).unlink()
        return row, files

    def close(self) -> None:
        close_worker()
        shutil.rmtree(self.stage, ignore_errors=True)


def _bytes_writer(data: bytes) -> Any:
    return lambda path: path.write_bytes(data)


def folder_files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by relative POSIX path (empty when it does not exist): what a Ray worker
    sends back, and what ``write_files`` writes."""
    if not folder.is_dir():
        return {}
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def write_files(folder: Path, files: dict[str, bytes]) -> None:
    """An episode's files into the campaign folder, atomically each, its row (``episodes/``) last."""
    for rel in sorted(files, key=lambda r: (r.startswith("episodes/"), r)):
        target = folder / rel
        if ".." in Path(rel).parts:
            raise RuntimeError(f"a worker sent a file outside the campaign folder: {rel}")
        atomic_write(target, _bytes_writer(files[rel]))


#: seconds a campaign that has lost every actor waits for a replacement to be placed before it stops
REPLACEMENT_WAIT_S = 120.0


@dataclass
class _Slot:
    """Worker slot i (its CARLA server, its Ray resources) and the actor that fills it now."""

    index: int
    actor: Any
    ready_ref: Any  # the actor's where(): resolves once it is up
    node: tuple[str, str] | None = None  # (node id, IP), once up
    task: int | None = None  # the task it runs now (index into tasks)
    ref: Any = None
    failed_starts: int = 0  # actors of this slot in a row that died before they were up


def _describe_episode(task: Any) -> str:
    return f"the episode of policy '{task[0]}' on scene {task[1]}"


class RayEpisodeScheduler:
    """Hands tasks to actors one at a time and gives a lost actor's task to another (module docstring). A task
    is an episode here; the benchmark hands whole campaigns to actors the same way (``benchmark.ray_campaigns``),
    with ``describe`` naming a task and ``unit`` what it is in messages."""

    def __init__(self, ray: Any, make_actor: Callable[[int], Any], slots: int, tasks: Sequence[Any],
                 max_losses: int, wait_s: float = REPLACEMENT_WAIT_S,
                 describe: Callable[[Any], str] = _describe_episode, unit: str = "episode",
                 watch: HeadWatch | None = None) -> None:
        from genesis_rl.distributed.ray_cluster import lost_errors

        self.ray, self.make_actor, self.tasks, self.max_losses, self.wait_s = ray, make_actor, tasks, max_losses, wait_s
        self.describe, self.unit = describe, unit
        self.watch = watch or HeadWatch(None)  # the cluster's head, asked while the driver waits
        self.lost_errors = lost_errors(ray)
        self.queue: deque[int] = deque(range(len(tasks)))
        self.losses: dict[int, int] = {}
        self.slots = [self._new_slot(i) for i in range(slots)]
        self.rerun = 0  # episodes that went back to the queue
        self.lost_nodes: list[str] = []

    def _new_slot(self, i: int, failed_starts: int = 0) -> _Slot:
        actor = self.make_actor(i)
        return _Slot(i, actor, actor.where.remote(), failed_starts=failed_starts)

    def run(self) -> Iterator[tuple[Any, dict[str, bytes]]]:
        try:
            yield from self._run()
        except RayHeadLost as err:
            raise _workers_lost(str(err), self.unit, RayHeadLost) from None

    def _run(self) -> Iterator[tuple[Any, dict[str, bytes]]]:
        from genesis_rl.distributed.ray_cluster import node_address

        stranded_since: float | None = None
        while self.queue or any(s.task is not None for s in self.slots):
            for slot in self.slots:  # every idle actor that is up takes the next episode
                if slot.node is not None and slot.task is None and self.queue:
                    slot.task = self.queue.popleft()
                    slot.ref = slot.actor.run.remote(self.tasks[slot.task])
            waiting = {s.ref if s.task is not None else s.ready_ref: s for s in self.slots
                       if s.task is not None or s.node is None}
            if not waiting:
                raise self._stranded()
            working = any(s.node is not None for s in self.slots)
            if working:
                stranded_since = None
            elif stranded_since is None:
                stranded_since = time.monotonic()
            left = None if working else max(0.0, self.wait_s - (time.monotonic() - (stranded_since or 0.0)))
            # never longer than the head's probe interval: a lost head fails no call, Ray ends the process
            ready, _ = self.ray.wait(list(waiting), num_returns=1,
                                     timeout=self.watch.every_s if left is None else min(left, self.watch.every_s))
            self.watch.check()
            if not ready:
                if left is not None and left <= self.watch.every_s:
                    raise self._stranded()
                continue
            slot = waiting[ready[0]]
            try:
                value = self.ray.get(ready[0])
            except self.lost_errors as err:
                if getattr(err, "actor_init_failed", False):
                    raise  # the actor's set-up failed (a plug-in, a setting): a replacement would fail the same way
                self._lose(slot, err)
                continue
            if slot.task is None:
                slot.node = (value[0], node_address(self.ray, value[0], value[1]))
            else:
                slot.task, slot.ref = None, None
                yield value

    def _lose(self, slot: _Slot, err: BaseException) -> None:
        """``slot``'s actor is gone: its episode (and those of every actor on the same node, if the node is gone)
        back to the queue, replacements asked for, one line on stderr."""
        from genesis_rl.distributed.ray_cluster import node_alive

        self.watch.confirm()  # a lost head takes its workers with it, and node_alive would wait on its GCS
        node_id, ip = slot.node or ("", "")
        node_gone = bool(node_id) and not node_alive(self.ray, node_id)
        victims = [s for s in self.slots if node_gone and s.node is not None and s.node[0] == node_id]
        victims = victims or [slot]
        episodes = []
        for s in victims:
            if s.task is not None:
                episodes.append(s.task)
                self.losses[s.task] = self.losses.get(s.task, 0) + 1
                if self.losses[s.task] > self.max_losses:
                    raise _workers_lost(f"{self.describe(self.tasks[s.task])} lost its Ray worker "
                                        f"{self.losses[s.task]} times (it may kill its worker: {_short(err)})",
                                        self.unit)
            try:
                self.ray.kill(s.actor)
            except Exception:  # noqa: BLE001 - a dead actor is killed already
                pass
            failed = s.failed_starts + 1 if s.node is None else 0
            if failed > self.max_losses:  # its actors die as they start: no more of them
                self.slots.remove(s)
            else:  # placed where the cluster has room
                self.slots[self.slots.index(s)] = self._new_slot(s.index, failed)
        self.queue.extendleft(reversed(episodes))  # the lost episodes first, in their order
        self.rerun += len(episodes)
        if not node_gone and not episodes and slot.node is None:
            return  # an actor that never came up (e.g. placed on a node going down) cost nothing to report
        where = f"Ray node {node_id or '?'} ({ip or 'unknown IP'})"
        live = sum(s.node is not None for s in self.slots)
        if node_gone:
            self.lost_nodes.append(f"{node_id} ({ip})")
            what = f"genesis-rl: lost {where}: {len(victims)} worker(s)"
        else:
            what = f"genesis-rl: a Ray worker on {where} died ({_short(err)})"
        print(f"{what}; {len(episodes)} {self.unit}(s) go back to the queue and run again on the {live} worker(s) "
              f"left or on replacements where the cluster has room", file=sys.stderr, flush=True)

    def _stranded(self) -> Exception:
        lost = f" (lost nodes: {', '.join(self.lost_nodes)})" if self.lost_nodes else ""
        whole = "benchmark" if self.unit == "campaign" else "campaign"
        return _workers_lost(f"every Ray worker of the {whole} is lost{lost} and no replacement could be placed "
                             f"within {self.wait_s:g} s; {len(self.queue)} {self.unit}(s) are not run", self.unit)

    def close(self) -> None:
        if self.watch.lost:
            return  # every call below needs the head's GCS, and would wait for it until Ray ends the process
        for s in self.slots:
            if s.node is not None:
                try:
                    self.ray.get(s.actor.close.remote(), timeout=30)
                except Exception:  # noqa: BLE001 - a dead actor has nothing left to close
                    pass
            try:
                self.ray.kill(s.actor)  # and one still waiting for room gives up its request
            except Exception:  # noqa: BLE001
                pass


def _short(err: BaseException) -> str:
    first = str(err).strip().splitlines()
    return f"{type(err).__name__}: {first[0][:160]}" if first else type(err).__name__


def _workers_lost(reason: str, unit: str = "episode", kind: type[RayWorkersLost] = RayWorkersLost) -> RayWorkersLost:
    command = "benchmark" if unit == "campaign" else "evaluate"
    where = ("(locally, or on Ray once the head is back)" if kind is RayHeadLost else
             "(on Ray or locally) once the cluster has room")
    return kind(f"{reason}; the finished {unit}s are kept: continue with genesis-rl {command} --resume {where}",
                reason)


def _run_ray(tasks: Sequence[Task], setup: WorkerSetup, settings: ExecutorSettings) -> Iterator[dict[str, Any]]:
    from genesis_rl.distributed.ray_cluster import driver_paths, ray_session

    retries = int(setup.spec_json.get("options", {}).get("retries", 2))
    n = min(settings.workers, len(tasks))
    if n == 0:
        return
    with ray_session(settings.ray_address, n, settings.ray_resources(0)) as ray:
        # no restarts by Ray: a lost actor is replaced by the scheduler, which knows its episode and its node
        remote = ray.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(EpisodeActor)
        # put once and held here for the whole campaign: replacement actors are built from the same objects
        setup_ref = ray.put(setup)
        catalog_ref = ray.put((setup.folder / "catalog.json").read_bytes())
        paths_ref = ray.put(driver_paths())

        def make(i: int) -> Any:
            return remote.options(resources=settings.ray_resources(i)).remote(setup_ref, catalog_ref,
                                                                              settings.server(i), paths_ref)

        scheduler = RayEpisodeScheduler(ray, make, n, tasks, max_losses=retries + 1,
                                        watch=HeadWatch.of(ray, settings.ray_address))
        try:
            for row, files in scheduler.run():
                write_files(setup.folder, files)
                yield row
        finally:
            scheduler.close()
