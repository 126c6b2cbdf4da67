"""Connecting to Ray: a local instance when no address is given, an existing cluster with one.

Ray is an optional extra (``pip install -e .[ray]``). Everything that can go wrong before a campaign or a
training run starts (Ray not installed, an address nobody answers, a cluster with fewer CPUs than the
workers asked for) is a :class:`UserInputError` raised *before* any output folder is touched, so a bad
``--ray-address`` writes nothing.

Without an address the command starts a Ray of its own (``address="local"``), whatever clusters run on the
machine: ``ray.init()`` would otherwise join the cluster a ``ray start --head`` left in
``/tmp/ray/ray_current_cluster`` (or ``RAY_ADDRESS``) and refuse the CPU count.

A node or worker lost mid-run raises one of :data:`LOST_ERROR_NAMES`; campaigns re-run that worker's episode
elsewhere (``evaluation/executors.py``), training stops at its last checkpoint (:class:`RayWorkersLost`).
"""

from __future__ import annotations

import os
import re
import socket
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType
from typing import Any

from genesis_rl.core.errors import UserInputError

#: seconds the --ray-address check may take (name lookup, connect, the server's first bytes) before ray.init,
#: which retries for 20 s and more against an address that does not answer as Ray
CONNECT_TIMEOUT_S = 3.0
#: an HTTP/2 client's opening (preface and an empty SETTINGS frame): Ray's GCS and client server speak gRPC,
#: whose servers answer it with a SETTINGS frame at once
HTTP2_HELLO = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_checked: set[str] = set()  # addresses that answered as gRPC in this process (preflight, then ray_session)
INSTALL_HINT = "install the extra: pip install -e .[ray] (or pip install ray)"
#: the ``ray.exceptions`` that mean "the actor, its worker process, its node or an object it held is gone"
#: (ActorDiedError and ActorUnavailableError are RayActorErrors; OwnerDiedError is an ObjectLostError). Not
#: LocalRayletDiedError: this process's own node is gone, and nothing here can go on.
LOST_ERROR_NAMES = ("RayActorError", "ActorDiedError", "ActorUnavailableError", "NodeDiedError", "WorkerCrashedError",
                    "ObjectLostError", "OwnerDiedError")


class RayWorkersLost(UserInputError):
    """Ray lost workers (or their nodes) and the run cannot go on; what is written is kept. The CLI prints the
    message (which names ``--resume``) as one line and exits with status 3, no traceback. ``reason``: what was
    lost, without what to do next (a command that removes its folder says "run the command again" instead)."""

    exit_code = 3

    def __init__(self, message: str, reason: str | None = None) -> None:
        super().__init__(message)
        self.reason = reason or message


def lost_errors(ray: ModuleType) -> tuple[type[BaseException], ...]:
    """The classes of :data:`LOST_ERROR_NAMES` this Ray version has."""
    found = (getattr(ray.exceptions, name, None) for name in LOST_ERROR_NAMES)
    return tuple(c for c in found if isinstance(c, type) and issubclass(c, BaseException))


def where_am_i() -> tuple[str, str]:
    """(node id, node IP) of the calling Ray worker."""
    import ray

    return ray.get_runtime_context().get_node_id(), ray.util.get_node_ip_address()


def _node(ray: ModuleType, node_id: str) -> dict[str, Any] | None:
    try:
        return next((n for n in ray.nodes() if n.get("NodeID") == node_id), None)
    except Exception:  # noqa: BLE001 - the GCS is busy or gone: nothing known about the node
        return None


def node_address(ray: ModuleType, node_id: str, fallback: str) -> str:
    """The IP the cluster knows ``node_id`` by (its raylet's, as `ray start --node-ip-address` set it)."""
    node = _node(ray, node_id)
    return str(node.get("NodeManagerAddress") or fallback) if node else fallback


def node_alive(ray: ModuleType, node_id: str | None, probe_s: float = 2.0) -> bool:
    """Whether ``node_id`` is still up: the cluster counts it alive *and* its raylet takes a TCP connection
    within ``probe_s`` (the cluster marks a node dead only after its health checks fail, ~15 s by default,
    while its actors' calls fail at once). True when nothing is known (a worker died, not a node)."""
    if not node_id:
        return True
    node = _node(ray, node_id)
    if node is None:
        return True
    if not node.get("Alive", True):
        return False
    host, port = node.get("NodeManagerAddress"), node.get("NodeManagerPort")
    if not host or not port:
        return True
    try:
        with socket.create_connection((str(host), int(port)), timeout=probe_s):
            return True
    except OSError:
        return False


def require_ray(flag: str = "--executor ray") -> ModuleType:
    """The ``ray`` module, or a clear error naming the extra that installs it."""
    try:
        import ray
    except ImportError:
        raise UserInputError(f"{flag} needs Ray, which is not installed here; {INSTALL_HINT}") from None
    return ray


def _host_port(address: str) -> tuple[str, int] | None:
    """The (host, port) an address names, or None for ``auto``/``local`` (Ray finds or starts those)."""
    if address in ("auto", "local"):
        return None
    rest = address.split("://", 1)[1] if "://" in address else address
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise UserInputError(f"--ray-address = '{address}'; allowed: HOST:PORT (a cluster's GCS, e.g. "
                             "10.0.0.5:6379), ray://HOST:PORT (Ray client, port 10001) or auto")
    return host, int(port)


def check_reachable(address: str) -> None:
    """Refuse, within about CONNECT_TIMEOUT_S, an address that does not resolve, refuses, cannot be reached or
    answers but not as a gRPC server (Ray's GCS is one): ``ray.init`` would retry for 20 s and more."""
    hp = _host_port(address)
    if hp is None or address in _checked:
        return
    from genesis_rl.core.netprobe import ProbeError, ask

    fix = "start the cluster's head (ray start --head) or leave --ray-address out for a local Ray"
    try:
        answer = ask(hp[0], hp[1], HTTP2_HELLO, 9, CONNECT_TIMEOUT_S)
    except ProbeError as err:
        what = {"unresolvable": f"'{hp[0]}' does not resolve ({err.detail})",
                "silent": f"{hp[0]}:{hp[1]} accepts connections but does not answer as Ray's GCS within "
                          f"{CONNECT_TIMEOUT_S:g} s (another service, or a firewall that holds the connection)",
                "closed": f"{hp[0]}:{hp[1]} closed the connection without answering: not Ray's GCS"
                }.get(err.kind, f"nothing answers at {hp[0]}:{hp[1]} ({err.detail})")
        raise UserInputError(f"--ray-address = '{address}': {what}; {fix}") from None
    frame = answer.data[:9]
    if len(frame) < 9 or frame[3] != 0x04:  # an HTTP/2 frame header whose type is SETTINGS
        raise UserInputError(f"--ray-address = '{address}': {hp[0]}:{hp[1]} answers, but not as Ray's GCS (a gRPC "
                             f"server; it sent {answer.data[:24]!r}); check the port (the head's GCS port, 6379 by "
                             f"default, or 10001 for ray://) or {fix}")
    if address.startswith("ray://"):
        _ping_client_server(address, hp[0], hp[1], max(0.5, CONNECT_TIMEOUT_S - answer.waited))
    _checked.add(address)


def _ping_client_server(address: str, host: str, port: int, timeout: float) -> None:
    """Ask a ``ray://`` address Ray Client's own first question (PING), on the channel ``ray.init`` would open
    (with the token it would send): Ray's client retries a refused PING for half a minute and more, then says
    only "ray client connection timeout"; the status tells a GCS port or another gRPC service (UNIMPLEMENTED)
    and a cluster that wants a token (UNAUTHENTICATED) at once."""
    try:
        import grpc
        from ray.core.generated import ray_client_pb2, ray_client_pb2_grpc
    except ImportError:  # a Ray without them: ray.init will tell
        return
    try:
        from ray._private.grpc_utils import init_grpc_channel  # Ray's own channel: its token and TLS settings
        channel = init_grpc_channel(f"{host}:{port}")
    except Exception:  # noqa: BLE001 - an older Ray: a plain channel still tells UNIMPLEMENTED apart
        channel = grpc.insecure_channel(f"{host}:{port}")
    try:
        pb2: Any = ray_client_pb2  # generated code, no types
        ray_client_pb2_grpc.RayletDriverStub(channel).ClusterInfo(
            pb2.ClusterInfoRequest(type=pb2.ClusterInfoType.PING), timeout=timeout)
    except grpc.RpcError as err:
        code = err.code() if callable(getattr(err, "code", None)) else None
        if code == grpc.StatusCode.UNIMPLEMENTED:
            raise UserInputError(f"--ray-address = '{address}': {host}:{port} is a gRPC server but not Ray's Client "
                                 f"server (ray:// needs the head's Ray Client port, 10001 unless ray start "
                                 f"--ray-client-server-port set another); a cluster's GCS port is given without "
                                 f"ray://: --ray-address {host}:{port}") from None
        if code == grpc.StatusCode.UNAUTHENTICATED:
            raise UserInputError(f"--ray-address = '{address}': the cluster wants a token (Ray's token "
                                 "authentication) and this command sent none or another; set RAY_AUTH_MODE=token "
                                 "here and give it the cluster's token (RAY_AUTH_TOKEN, or ~/.ray/auth_token as on "
                                 "the head)") from None
        details = " ".join(str(err.details() if callable(getattr(err, "details", None)) else err).split())
        raise UserInputError(f"--ray-address = '{address}': the Ray Client server at {host}:{port} did not answer "
                             f"its ping ({code.name if code else 'error'}: {details[:200]}); check that the head's "
                             "Ray Client server runs there, or connect to the cluster's GCS (--ray-address "
                             "HOST:6379)") from None
    finally:
        channel.close()


def connect_error(address: str, err: BaseException) -> UserInputError:
    """``ray.init``'s refusal as one line. Ray Client's refusals carry the server's whole traceback ("Initialization
    failure from server:" and the lines of the head's proxy): its last line says what failed."""
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    if "Traceback (most recent call last):" in lines:
        last = lines[-1]
        cause = last.split(": ", 1)[1] if re.match(r"^[\w.]+(Error|Exception): ", last) else last
        cause = cause[:300].rstrip(".")
        logs = "" if "session_latest/logs" in cause else \
            "; Ray's logs are on the head, in /tmp/ray/session_latest/logs by default"
        return UserInputError(f"--ray-address = '{address}': the Ray Client server there could not start this "
                              f"command's session (Ray: \"{cause}\"{logs}); run the command again, or connect without "
                              "Ray Client: --ray-address HOST:6379 (the head's GCS port) from a machine that reaches "
                              "every node, or auto on the head")
    return UserInputError(f"--ray-address = '{address}': Ray could not connect ({' '.join(lines)[:300]})")


def driver_paths() -> list[str]:
    """This process's import path: workers on this machine add it, so user plug-in modules (policies, rules,
    knobs) found here resolve in Ray workers too. Paths a remote node lacks are skipped there."""
    return [p for p in sys.path if p and os.path.isdir(p)]


def add_driver_paths(paths: list[str]) -> None:
    for p in reversed(paths):
        if p not in sys.path and os.path.isdir(p):
            sys.path.insert(0, p)


@contextmanager
def ray_session(address: str | None, workers: int, per_worker: dict[str, float] | None = None
                ) -> Iterator[ModuleType]:
    """Ray, initialised for the duration: a local instance with at least ``workers`` CPUs when ``address`` is
    None, else the cluster at ``address``; an instance this process already started is reused and kept. The
    cluster must offer ``workers`` times each custom resource of ``per_worker`` (a worker's CARLA server)."""
    ray = require_ray()
    started = False
    # ray.init puts its own SIGTERM handler (sys.exit) in this process and shutdown leaves it there: a later
    # command in the same process (tests, a notebook) would lose its Interrupted and its deferred writes
    handlers = _signal_handlers()
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                  "configure_logging": True, "logging_level": "ERROR"}
        if address:
            check_reachable(address)
            try:
                with warnings.catch_warnings():  # Ray Client warns in several lines before it raises
                    warnings.simplefilter("ignore")
                    ray.init(address=address, **kwargs)
            except (ConnectionError, RuntimeError, ValueError) as err:
                raise connect_error(address, err) from None
        else:
            # "local": a new instance even where a `ray start` cluster (or a stale address file) exists
            ray.init(address="local", num_cpus=max(workers, os.cpu_count() or 1), **kwargs)
        started = True
    try:
        cpus = float(ray.cluster_resources().get("CPU", 0))
        if cpus < workers:
            raise UserInputError(f"--workers = {workers} but the Ray cluster has {cpus:g} CPUs; each worker takes "
                                 f"one: allowed --workers 1..{int(cpus)}, or add nodes")
        for name, amount in (per_worker or {}).items():
            have = float(ray.cluster_resources().get(name, 0))
            if have < workers * amount:  # Ray would wait for them forever
                raise UserInputError(
                    f"{workers} workers each need a '{name}' resource but the Ray cluster offers {have:g}; start "
                    f"each node that runs a CARLA server with ray start --resources='{{\"{name}\": 1}}', or use "
                    f"at most {int(have // amount)} workers")
        yield ray
    finally:
        if started:
            ray.shutdown()
            _restore_signal_handlers(handlers)


def _signal_handlers() -> dict[int, Any]:
    """SIGINT's and SIGTERM's handlers now (none off the main thread, where they cannot be set)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    return {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}


def _restore_signal_handlers(handlers: dict[int, Any]) -> None:
    import signal

    for signum, handler in handlers.items():
        if handler is not None:
            signal.signal(signum, handler)
