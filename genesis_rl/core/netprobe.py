"""Asking a TCP service what it is, within a deadline, before a client library is pointed at it.

Client libraries wait long or worse when the address is wrong: ``ray.init`` retries for 20 s and more against
anything that accepts a connection, and the CARLA client aborts the whole process (exit 134) when the port
answers with something that is not msgpack-rpc. :func:`ask` resolves the host, connects, sends one request and
reads the first bytes of the answer, every step bounded by one deadline, and says which step failed
(:class:`ProbeError` ``kind``): ``unresolvable``, ``refused``, ``unreachable``, ``timeout`` (connect),
``silent`` (connected, no answer in time) or ``closed`` (connected, closed without answering).
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass


class ProbeError(Exception):
    """A probe that got no answer; ``kind`` says where it stopped, ``detail`` the system's words."""

    def __init__(self, kind: str, detail: str, waited: float) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind, self.detail, self.waited = kind, detail, waited


@dataclass(frozen=True)
class Answer:
    data: bytes  # the first bytes the service sent (at least ``want`` unless it closed first)
    waited: float  # seconds from the start of the probe


def resolve(host: str, port: int, timeout: float) -> list[tuple]:
    """The addresses of ``host`` (getaddrinfo, which has no timeout of its own, run in a thread)."""
    found: list = []
    failed: list[BaseException] = []

    def lookup() -> None:
        try:
            found.extend(socket.getaddrinfo(host, port, type=socket.SOCK_STREAM))
        except (OSError, UnicodeError) as err:
            failed.append(err)

    worker = threading.Thread(target=lookup, daemon=True, name="genesis-rl-resolve")
    t0 = time.monotonic()
    worker.start()
    worker.join(timeout)
    waited = time.monotonic() - t0
    if worker.is_alive():
        raise ProbeError("unresolvable", f"the name lookup took more than {timeout:g} s", waited)
    if failed or not found:
        raise ProbeError("unresolvable", str(failed[0]) if failed else "no address", waited)
    return found


def ask(host: str, port: int, request: bytes, want: int, timeout: float, answer_timeout: float | None = None
        ) -> Answer:
    """Connect to ``host:port`` within ``timeout`` (name lookup included), send ``request`` (may be empty) and
    read until ``want`` bytes arrived, the service closed, or ``answer_timeout`` (default: ``timeout``) passed."""
    t0 = time.monotonic()
    addresses = resolve(host, port, timeout)
    last: ProbeError | None = None
    sock: socket.socket | None = None
    for family, kind, proto, _, address in addresses:
        left = timeout - (time.monotonic() - t0)
        if left <= 0:
            break
        candidate = socket.socket(family, kind, proto)
        candidate.settimeout(left)
        try:
            candidate.connect(address)
        except TimeoutError:
            candidate.close()
            last = ProbeError("timeout", f"no answer to the connection within {timeout:g} s", time.monotonic() - t0)
            continue
        except ConnectionRefusedError as err:
            candidate.close()
            last = ProbeError("refused", err.strerror or str(err), time.monotonic() - t0)
            continue
        except OSError as err:
            candidate.close()
            last = ProbeError("unreachable", err.strerror or str(err), time.monotonic() - t0)
            continue
        sock = candidate
        break
    if sock is None:
        raise last or ProbeError("timeout", f"no answer to the connection within {timeout:g} s",
                                 time.monotonic() - t0)
    window = timeout if answer_timeout is None else answer_timeout
    deadline = time.monotonic() + window
    data = b""
    try:
        if request:
            sock.settimeout(max(0.01, deadline - time.monotonic()))
            sock.sendall(request)
        while len(data) < want:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            sock.settimeout(left)
            chunk = sock.recv(4096)
            if not chunk:
                if not data:
                    raise ProbeError("closed", "the connection was closed without an answer", time.monotonic() - t0)
                break
            data += chunk
    except TimeoutError:
        pass
    except OSError as err:  # reset by the peer, broken pipe
        if not data:
            raise ProbeError("closed", err.strerror or str(err), time.monotonic() - t0) from None
    finally:
        sock.close()
    if not data:
        raise ProbeError("silent", f"connected, but no answer within {window:g} s", time.monotonic() - t0)
    return Answer(data, time.monotonic() - t0)
