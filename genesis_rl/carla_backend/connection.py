"""Connecting to a CARLA server, with errors a user can act on.

The client raises a bare ``RuntimeError("time-out of 1000ms while waiting for the simulator ...")`` when no
server answers; we turn that into a :class:`CarlaConnectionError` (a :class:`UserInputError`, so the CLI prints
it and exits with status 2) that names host:port and how to start a server. A server that stops answering
mid-episode raises :class:`CarlaServerLost`, which a campaign can catch to reconnect and retry the episode.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

from genesis_rl import ranges
from genesis_rl.carla_backend._carla import require_carla
from genesis_rl.errors import SimulatorLost, UserInputError

T = TypeVar("T")

#: The client version this backend is written and tested against.
CLIENT_VERSION = "0.9.16"


class CarlaConnectionError(UserInputError):
    """No CARLA server answered at host:port (down, starting, wrong port or firewalled)."""


class CarlaServerLost(SimulatorLost):
    """The server stopped answering during an episode; the episode is lost, the backend must reconnect."""


def start_hint(host: str, port: int) -> str:
    return (
        f"start a CARLA {CLIENT_VERSION} server, e.g. './CarlaUE4.sh -RenderOffScreen -carla-rpc-port={port}' "
        f"or 'docker run --privileged --gpus all --net=host carlasim/carla:{CLIENT_VERSION} "
        f"bash CarlaUE4.sh -RenderOffScreen -carla-rpc-port={port}' (see docs/carla.md), wait until it listens, "
        f"or point --carla-host/--carla-port at a running one (now {host}:{port})"
    )


def connect(host: str, port: int, timeout: float) -> Any:
    """A ``carla.Client`` that has answered once (``get_server_version``), with ``timeout`` on every call."""
    carla = require_carla()
    if not 1 <= int(port) <= 65535:
        raise UserInputError(f"--carla-port {port} is not a TCP port (1..65535)")
    timeout = ranges.TIMEOUT.check(timeout, "CARLA timeout (--carla-timeout, env.carla_timeout)")
    client = carla.Client(str(host), int(port))
    client.set_timeout(float(timeout))
    t0 = time.monotonic()
    try:
        server_version = client.get_server_version()
    except RuntimeError as err:
        waited = time.monotonic() - t0
        raise CarlaConnectionError(
            f"no CARLA server answered at {host}:{port} within {waited:.1f} s (client: {err}); "
            + start_hint(host, port)
        ) from None
    client_version = client.get_client_version()
    if server_version.split("-")[0] != client_version.split("-")[0]:
        warnings.warn(
            f"CARLA server {host}:{port} runs {server_version} but the client is {client_version}; "
            "mismatched versions can fail in odd ways: install the matching client (pip install carla==<server>)",
            RuntimeWarning,
            stacklevel=2,
        )
    return client


def is_connection_error(err: BaseException) -> bool:
    """The client reports both time-outs and refused/broken connections as RuntimeError; tell them from
    other RuntimeErrors (a bad blueprint, an invalid spawn) by their text."""
    text = str(err).lower()
    return any(k in text for k in ("time-out", "timeout", "connect", "rpc::", "broken pipe", "closed"))


def guarded(host: str, port: int, what: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """Call ``fn``; a client time-out or lost connection becomes :class:`CarlaServerLost` naming ``what``."""
    try:
        return fn(*args, **kwargs)
    except RuntimeError as err:
        if not is_connection_error(err):
            raise
        raise CarlaServerLost(
            f"CARLA server {host}:{port} stopped answering while {what} ({err}); the episode is lost. "
            "Check the server's log (it may have crashed or run out of GPU memory) and restart it; "
            + start_hint(host, port)
        ) from err
