"""A pool of spawned worker processes that cannot leave the parent waiting.

``multiprocessing.Pool`` starts a new worker whenever one exits, so a worker whose initializer raises (a
plug-in that does not import, a campaign spec it cannot read) is started again forever and the parent never
hears why. Here a worker keeps its initializer's error and raises it in its first task, so the error reaches
the parent through the task's result. Workers ignore Ctrl-C, which a terminal sends to every process of the
command: it is the parent's to handle (it terminates the pool, and what was written stays resumable).
The campaign's episode pool, reactivity's pool, the benchmark's side-by-side campaigns and the estimate's
episodes all start here.
"""

from __future__ import annotations

import multiprocessing as mp
import signal
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

#: this worker's initializer error, if it had one (raised by every task the worker is given)
_FAILED: list[BaseException] = []


def _start(initializer: Callable[..., None], initargs: Sequence[Any]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        initializer(*initargs)
    except Exception as err:  # noqa: BLE001 - handed to the parent by the worker's first task
        _FAILED.append(err)


@dataclass(frozen=True)
class _Guarded:
    """``fn`` in a worker, unless the worker could not start: then its initializer's error."""

    fn: Callable[[Any], Any]

    def __call__(self, job: Any) -> Any:
        if _FAILED:
            raise _FAILED[0]
        return self.fn(job)


class SpawnPool:
    """``processes`` spawned workers, each set up by ``initializer(*initargs)`` (module-level, so it pickles).
    As a context manager it terminates the workers on leaving, as ``multiprocessing.Pool`` does."""

    def __init__(self, processes: int, initializer: Callable[..., None], initargs: Sequence[Any] = ()) -> None:
        self._pool = mp.get_context("spawn").Pool(processes, initializer=_start,
                                                  initargs=(initializer, tuple(initargs)))

    def imap(self, fn: Callable[[Any], Any], jobs: Iterable[Any]) -> Iterator[Any]:
        """``fn`` over ``jobs`` on the workers, results in the jobs' order."""
        return self._pool.imap(_Guarded(fn), jobs)

    def imap_unordered(self, fn: Callable[[Any], Any], jobs: Iterable[Any]) -> Iterator[Any]:
        """``fn`` over ``jobs`` on the workers, results as they finish."""
        return self._pool.imap_unordered(_Guarded(fn), jobs)

    def close(self) -> None:
        """Let the workers exit on their own once their tasks are done (they release what they hold;
        ``terminate`` leaks a semaphore warning at exit), and wait for them."""
        self._pool.close()
        self._pool.join()

    def terminate(self) -> None:
        """Stop the workers now (Ctrl-C, or an error in a task) and wait for them."""
        self._pool.terminate()
        self._pool.join()

    def __enter__(self) -> SpawnPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.terminate()
