"""The traffic manager's port: one per run, derived from its server's, and free on this machine.

The traffic manager is an RPC server that ``client.get_trafficmanager(port)`` opens on the *client's*
machine. Two runs on one machine with the same traffic-manager port collide: the second fails after about
10 s with CARLA's "bind error", a bare RuntimeError. So each run's port defaults to its server's RPC port +
:data:`TM_PORT_OFFSET` (2000 -> 8000, 3000 -> 9000), and the port is checked before the client is asked.
A CARLA server itself listens on its RPC port, RPC+1 (streaming) and RPC+2 (secondary), never on 8000.
"""

from __future__ import annotations

import os
import socket

from genesis_rl.core.errors import UserInputError

#: CARLA's defaults put the traffic manager 6000 above the RPC port (2000 -> 8000)
TM_PORT_OFFSET = 6000


class TrafficManagerPortBusy(UserInputError):
    """The traffic manager's port is taken on this machine (another run's traffic manager, or a service)."""


def default_tm_port(port: int, tm_port: int | None = None) -> int:
    """``tm_port`` when given, else the server's RPC ``port`` + :data:`TM_PORT_OFFSET`."""
    if tm_port is not None:
        return int(tm_port)
    derived = int(port) + TM_PORT_OFFSET
    if derived > 65535:
        raise UserInputError(f"--carla-tm-port (env.carla_tm_port) is not given and --carla-port {port} + "
                             f"{TM_PORT_OFFSET} = {derived} is not a port; allowed: give --carla-tm-port 1..65535")
    return derived


def busy_message(tm_port: int, detail: str) -> str:
    return (f"the traffic manager's port {tm_port} is taken on this machine ({detail}): another run's traffic "
            "manager holds it, or another service. Each run needs its own: leave --carla-tm-port "
            "(env.carla_tm_port) unset so it is --carla-port + 6000, or give a free one")


def ensure_free(tm_port: int) -> None:
    """Raise :class:`TrafficManagerPortBusy` when nothing could listen on ``tm_port`` here (what the traffic
    manager is about to do): a fast, named failure instead of CARLA's bind error."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        if os.name != "nt":  # as the traffic manager's acceptor; on Windows the option would steal the port
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("", int(tm_port)))
        sock.listen(1)
    except OSError as err:
        raise TrafficManagerPortBusy(busy_message(tm_port, err.strerror or str(err))) from None
    finally:
        sock.close()


def is_bind_error(err: BaseException) -> bool:
    """CARLA's "trying to create rpc server for traffic manager; but the system failed to create because of
    bind error" (a RuntimeError that no connection check recognises)."""
    return "bind error" in str(err).lower()


def free_port() -> int:
    """A port that nothing listens on here now (the system's pick), for a connection whose configured
    traffic-manager port is held by a lost server's traffic manager in this process."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.bind(("", 0))
        return int(sock.getsockname()[1])
    finally:
        sock.close()
