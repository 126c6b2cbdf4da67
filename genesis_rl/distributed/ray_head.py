"""Noticing that a Ray cluster's head is gone while a run waits on the cluster.

Ray's driver does not report a lost head: its calls to the GCS (the head's control store) retry, and 60 s
after the GCS last answered Ray ends the whole process from C++ ("Failed to connect to GCS within 60
seconds ... The program will terminate"). No ``finally`` runs then: the output folder's lock stays behind
and no line names ``--resume``. So a run on Ray asks the head itself, outside Ray: every
``HEAD_PROBE_EVERY_S`` while it waits, and before any call that needs the GCS after a worker was lost, a TCP
connection and the gRPC opening to the GCS (what ``check_reachable`` asks before ``ray.init``). A head silent
for ``HEAD_LOST_AFTER_S`` is lost: :class:`RayHeadLost` (exit 3, one line), raised well before Ray's 60 s, and
the run's clean-up makes no further call that needs the GCS (``HeadWatch.lost``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from types import ModuleType

from genesis_rl.distributed.ray_cluster import HTTP2_HELLO, RayWorkersLost

#: seconds between two questions to the head while a run waits on Ray
HEAD_PROBE_EVERY_S = 1.0
#: seconds the head may stay silent before the run counts it lost: a busy head answers the gRPC opening within
#: milliseconds, a head that is gone does not come back (unless :func:`lost_after_s` says otherwise), and Ray
#: ends the process itself once its GCS has been silent for 60 s
HEAD_LOST_AFTER_S = 10.0
#: Ray's own limit on a silent GCS, which a cluster with GCS fault tolerance raises so that its drivers outlive a
#: restarting head (KubeRay sets it to 600 s)
RAY_GCS_TIMEOUT_ENV = "RAY_gcs_rpc_server_reconnect_timeout_s"


class RayHeadLost(RayWorkersLost):
    """The cluster's head (its GCS) stopped answering: the run cannot go on; exit 3, one line."""


def head_address(ray: ModuleType, given: str | None) -> str | None:
    """HOST:PORT of the head a session connected to with ``--ray-address`` ``given`` (None: a local Ray): the
    Ray Client server's for ``ray://``, else the GCS's as Ray reports it; None when Ray does not say (a
    stand-in Ray in tests)."""
    if given and given.startswith("ray://"):
        host, _, port = given[len("ray://"):].rpartition(":")
        return f"{host}:{port}"
    try:
        return str(ray.get_runtime_context().gcs_address) or None
    except Exception:  # noqa: BLE001 - nothing known: no watch
        return None


def answers(address: str, timeout: float = HEAD_PROBE_EVERY_S) -> bool:
    """Whether a gRPC server (Ray's GCS or client server) answers at HOST:PORT within ``timeout``."""
    from genesis_rl.core.netprobe import ProbeError, ask

    host, _, port = address.rpartition(":")
    try:
        answer = ask(host.strip("[]"), int(port), HTTP2_HELLO, 9, timeout)
    except (ProbeError, ValueError):
        return False
    return len(answer.data) >= 9 and answer.data[3] == 0x04  # an HTTP/2 SETTINGS frame


def lost_after_s() -> float:
    """How long a head may be silent: :data:`HEAD_LOST_AFTER_S`, or, where the environment raises Ray's own
    limit (GCS fault tolerance: the head comes back), 5 s less than that limit, so that the run still stops
    with its line before Ray ends the process."""
    try:
        ray_limit = float(os.environ.get(RAY_GCS_TIMEOUT_ENV, ""))
    except ValueError:
        return HEAD_LOST_AFTER_S
    return max(HEAD_LOST_AFTER_S, ray_limit - 5.0)


class HeadWatch:
    """Asks the head at ``address`` whether it is up (``probe``, default :func:`answers`); ``address`` None
    watches nothing."""

    def __init__(self, address: str | None, probe: Callable[[str], bool] = answers,
                 lost_after: float | None = None, every_s: float = HEAD_PROBE_EVERY_S) -> None:
        self.address, self.probe, self.every_s = address, probe, every_s
        self.lost_after_s = lost_after_s() if lost_after is None else lost_after
        self.last_probe = time.monotonic()
        self.silent_since: float | None = None  # the first unanswered question since the last answer
        self.lost = False  # found lost: the run's clean-up makes no call that needs the head

    @classmethod
    def of(cls, ray: ModuleType, given: str | None) -> HeadWatch:
        """The watch of the head a session started with ``--ray-address`` ``given`` connected to."""
        return cls(head_address(ray, given))

    def check(self) -> None:
        """Ask the head if it was not asked within ``every_s``; :meth:`confirm` if it does not answer."""
        if self.address is None or time.monotonic() - self.last_probe < self.every_s:
            return
        self.confirm()

    def confirm(self) -> None:
        """Ask the head now, and again every ``every_s`` while it is silent: return once it answers, raise
        :class:`RayHeadLost` once it has been silent for ``lost_after_s``."""
        if self.address is None:
            return
        if self.lost:
            raise self._error()
        while True:
            self.last_probe = time.monotonic()
            if self.probe(self.address):
                self.silent_since = None
                return
            if self.silent_since is None:
                self.silent_since = self.last_probe
            if time.monotonic() - self.silent_since >= self.lost_after_s:
                self.lost = True
                raise self._error()
            time.sleep(max(0.0, self.every_s - (time.monotonic() - self.last_probe)))

    def _error(self) -> RayHeadLost:
        return RayHeadLost(f"lost the Ray cluster's head: nothing has answered at {self.address} for "
                           f"{self.lost_after_s:g} s")
