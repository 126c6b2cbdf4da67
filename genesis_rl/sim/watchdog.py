"""A deadline around every blocking call into a simulator server, so a hung server costs one episode.

A client's own time-out does not cover every wait: CARLA's ``world.tick(timeout)`` can block for ever
inside the traffic manager's untimed wait (CARLA issue #9172), and then a campaign's retry never fires.
:class:`Watchdog` runs each call on a daemon thread and stops waiting at its deadline: the call raises
:class:`SimulatorHung` (a :class:`~genesis_rl.core.errors.SimulatorLost`, which a campaign retries on a fresh
connection) and the connection is marked lost: every later call fails at once instead of queueing behind
the stuck one. Python cannot stop the stuck thread; it holds the client object, so whatever it needs is
kept alive for the rest of the process (:meth:`Watchdog.abandon`): a client library freed under a thread
still inside it, or a destructor that calls a dead server, can take the whole process down.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable
from typing import Any, TypeVar

from genesis_rl.core.errors import SimulatorLost

T = TypeVar("T")

#: objects of lost connections, never freed (see the module doc); their references are also leaked so
#: that not even interpreter shutdown runs their destructors
_ABANDONED: list[Any] = []


class SimulatorHung(SimulatorLost):
    """A server call did not return by its deadline: the connection is abandoned, the episode lost."""


def deadline_for(timeout: float) -> float:
    """The watchdog's deadline for a call the client itself bounds by ``timeout`` seconds: twice that and
    5 s more, so the client's own time-out (a clearer message) always fires first when it can."""
    return 2.0 * float(timeout) + 5.0


class Watchdog:
    """Deadlines for one connection's blocking calls; ``where`` names the server in messages."""

    def __init__(self, where: str) -> None:
        self.where = where
        self.lost: str | None = None  # why the connection was given up, once it was

    def call(self, what: str, deadline_s: float, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """``fn(*args, **kwargs)``, or :class:`SimulatorHung` when it has not returned in ``deadline_s``
        seconds (or an earlier call of this connection did not)."""
        if self.lost is not None:
            raise SimulatorHung(f"{self.where}: not asked to {what}: the connection was given up ({self.lost})")
        box: dict[str, Any] = {}
        done = threading.Event()

        def run() -> None:
            try:
                box["value"] = fn(*args, **kwargs)
            except BaseException as err:  # noqa: BLE001 - handed to the caller's thread as it is
                box["error"] = err
            finally:
                done.set()

        threading.Thread(target=run, name=f"watchdog {self.where}: {what}", daemon=True).start()
        if not done.wait(deadline_s):
            self.lost = f"{what} did not return within {deadline_s:g} s"
            raise SimulatorHung(f"{self.where} stopped answering: {self.lost} (the watchdog's deadline); the "
                                "episode is lost and the connection given up")
        if "error" in box:
            raise box["error"]
        return box["value"]

    def abandon(self, *objects: Any) -> None:
        """Keep ``objects`` (a client, its traffic manager) alive until the process ends, destructors never
        run: a thread may still be inside them, and their destructors may call the dead server."""
        for obj in objects:
            if obj is not None:
                _ABANDONED.append(obj)
                ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))
