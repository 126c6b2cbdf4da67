"""Connecting to a CARLA server, with errors a user can act on.

The client raises a bare ``RuntimeError("time-out of 1000ms while waiting for the simulator ...")`` when no
server answers; we turn that into a :class:`CarlaConnectionError` (a :class:`UserInputError`, so the CLI prints
it and exits with status 2) that names host:port and how to start a server. A server that stops answering
mid-episode raises :class:`CarlaServerLost`, which a campaign can catch to reconnect and retry the episode.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

from genesis_rl.core import ranges
from genesis_rl.core.errors import SimulatorLost, UserInputError
from genesis_rl.sim.carla._carla import require_carla

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


#: the longest --carla-timeout taken: a map loads in about a minute; an hour means something else is wrong
MAX_TIMEOUT_S = ranges.TIMEOUT.high  # one ceiling with the --carla-timeout flag's
#: seconds the probe may take to find and connect to the server (the answer gets --carla-timeout)
PROBE_CONNECT_S = 5.0
#: CARLA's RPC is msgpack-rpc (rpclib): the request [0, msgid 0, "version", [[false]]], hand-encoded (fixarray
#: of 4, fixint 0, fixint 0, fixstr of 7, then the arguments: CARLA's call metadata [asynchronous = false]).
#: It is the call the client's get_server_version() sends, byte for byte but the msgid (client 0.9.16).
VERSION_REQUEST = bytes([0x94, 0x00, 0x00, 0xA7]) + b"version" + bytes([0x91, 0x91, 0xC2])
#: a msgpack-rpc answer to it: [1 (response), msgid 0, error, result], error nil when the call exists
_RESPONSE_HEAD = bytes([0x94, 0x01, 0x00])
_NIL = 0xC0


def check_numbers(port: int, timeout: float, tm_port: int | None = None) -> None:
    """The connection's numbers, checked before any socket is opened: ports 1..65535, a timeout of finite
    seconds in (0, MAX_TIMEOUT_S] (the client turns inf into 0 s, which fails every call at once)."""
    for flag, value in (("--carla-port", port), ("--carla-tm-port", tm_port)):
        if value is not None and not (isinstance(value, int) and ranges.PORT.low <= value <= ranges.PORT.high):
            raise UserInputError(f"{flag} (env.{flag[2:].replace('-', '_')}) = {value} is not a TCP port; allowed: "
                                 "1..65535")
    if not (isinstance(timeout, int | float) and math.isfinite(timeout) and 0 < timeout <= MAX_TIMEOUT_S):
        raise UserInputError(f"--carla-timeout (env.carla_timeout) = {timeout} s; allowed: seconds in "
                             f"(0, {MAX_TIMEOUT_S:g}]")


def probe(host: str, port: int, timeout: float) -> None:
    """Ask ``host:port`` for CARLA's version over msgpack-rpc before a ``carla.Client`` is made: the client
    library aborts the whole process (exit 134) when the port answers with anything else, and reports a host
    that does not resolve as a bare RuntimeError. Each way of failing is one :class:`CarlaConnectionError`."""
    from genesis_rl.core.netprobe import ProbeError, ask

    where = f"{host}:{port}"
    try:
        answer = ask(host, port, VERSION_REQUEST, 4, min(timeout, PROBE_CONNECT_S), answer_timeout=timeout)
    except ProbeError as err:
        message = {
            "unresolvable": f"--carla-host '{host}' does not resolve ({err.detail}); check the name or give the "
                            "server's IP address",
            "refused": f"nothing listens at {where} (connection refused); " + start_hint(host, port),
            "unreachable": f"{where} cannot be reached ({err.detail}); check --carla-host and the network",
            "timeout": f"{where} did not accept a connection within {err.waited:.1f} s (no machine at that "
                       "address, or a firewall drops the connection); check --carla-host and --carla-port",
            "silent": f"{where} accepted the connection but did not answer CARLA's version call within "
                      f"{timeout:g} s (--carla-timeout): a server still starting or loading a map, or another "
                      "service on that port; wait and try again, or check --carla-port (CARLA's RPC port, 2000 by "
                      "default)",
            "closed": f"{where} closed the connection without answering CARLA's version call: not a CARLA server; "
                      "check --carla-port (CARLA's RPC port, 2000 by default)",
        }[err.kind]
        raise CarlaConnectionError(message) from None
    if not answer.data.startswith(_RESPONSE_HEAD):
        raise CarlaConnectionError(f"{where} answers, but not as a CARLA server (not msgpack-rpc: it sent "
                                   f"{answer.data[:32]!r}); check --carla-port (CARLA's RPC port, 2000 by default; "
                                   "the traffic manager's and the streaming port are others)")
    if answer.data[3] != _NIL:
        raise CarlaConnectionError(f"{where} is an RPC server without CARLA's 'version' call: not a CARLA server; "
                                   "check --carla-port (CARLA's RPC port, 2000 by default)")


def connect(host: str, port: int, timeout: float, tm_port: int | None = None) -> Any:
    """A ``carla.Client`` that has answered once (``get_server_version``), with ``timeout`` on every call; the
    port is probed first (:func:`probe`), so that the client library only ever meets a CARLA server."""
    carla = require_carla()
    check_numbers(port, timeout, tm_port)
    probe(str(host), int(port), float(timeout))
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
