"""CARLA servers for parallel workers: one server per worker, never two workers on one server.

A CARLA server accepts one client that ticks it in synchronous mode and one traffic-manager server per port,
so a campaign with ``--workers N`` (or a training run with ``--envs N``) on ``--backend carla`` needs N
servers, named with ``--carla-servers HOST:PORT[:TM_PORT],...``. Worker i (a pool process, a Ray actor or a
training env) drives server i. The lite backend needs none and ignores the list.

On a Ray cluster the servers can instead be Ray resources (``--carla-servers ray[:PORT[:TM_PORT]]``): each
node that runs a CARLA server is started with ``ray start --resources='{"carla_server": 1}'``, every worker
asks Ray for one ``carla_server`` and drives the server of the node it lands on, at 127.0.0.1:PORT. Ray then
never places two workers on one server, and a lost node's worker restarts where a server is free.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.carla.ports import TM_PORT_OFFSET

FORMAT = "HOST:PORT[:TM_PORT],... (e.g. localhost:2000,localhost:3000), or ray[:PORT[:TM_PORT]]"
#: the Ray resource a node offers per CARLA server it runs
RAY_RESOURCE = "carla_server"


@dataclass(frozen=True)
class CarlaServer:
    host: str
    port: int  # RPC port
    tm_port: int  # traffic manager port

    def env_settings(self) -> dict[str, Any]:
        """The ``[env]`` keys that point an env at this server."""
        return {"carla_host": self.host, "carla_port": self.port, "carla_tm_port": self.tm_port}

    def ray_resources(self) -> dict[str, float]:
        return {}

    def __str__(self) -> str:
        return f"{self.host}:{self.port}:{self.tm_port}"


@dataclass(frozen=True)
class NodeServer(CarlaServer):
    """The CARLA server of whichever Ray node the worker lands on: the worker holds one ``carla_server``
    resource of that node (so no other worker drives the same server) and connects to it locally."""

    host: str = "127.0.0.1"
    port: int = 2000
    tm_port: int = 2000 + TM_PORT_OFFSET

    def ray_resources(self) -> dict[str, float]:
        return {RAY_RESOURCE: 1.0}

    def __str__(self) -> str:
        return f"ray:{self.port}:{self.tm_port} (one '{RAY_RESOURCE}' resource per worker)"


def _port(text: str, item: str, flag: str) -> int:
    if not text.isdigit() or not 1 <= int(text) <= 65535:
        raise UserInputError(f"{flag}: '{item}' has port '{text}'; allowed: 1..65535, as {FORMAT}")
    return int(text)


def parse_servers(text: str | None, flag: str = "--carla-servers") -> tuple[CarlaServer, ...]:
    """``HOST:PORT[:TM_PORT],...`` as servers; the traffic-manager port defaults to PORT + 6000."""
    if text is None:
        return ()
    if text.strip() == "ray" or text.strip().startswith("ray:"):
        parts = text.strip().split(":")
        if len(parts) > 3:
            raise UserInputError(f"{flag}: '{text}' is not a server; allowed: {FORMAT}")
        port = _port(parts[1], text, flag) if len(parts) > 1 else 2000
        tm = _port(parts[2], text, flag) if len(parts) > 2 else port + TM_PORT_OFFSET
        if tm > 65535:
            raise UserInputError(f"{flag}: '{text}': the default traffic-manager port {tm} (PORT + 6000) is not a "
                                 "port; give it as ray:PORT:TM_PORT")
        return (NodeServer(port=port, tm_port=tm),)
    servers: list[CarlaServer] = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        parts = item.split(":")
        if len(parts) not in (2, 3) or not parts[0]:
            raise UserInputError(f"{flag}: '{item}' is not a server; allowed: {FORMAT}")
        port = _port(parts[1], item, flag)
        tm = _port(parts[2], item, flag) if len(parts) == 3 else port + TM_PORT_OFFSET
        if tm > 65535:
            raise UserInputError(f"{flag}: '{item}': the default traffic-manager port {tm} (PORT + 6000) is not a "
                                 "port; give it as HOST:PORT:TM_PORT")
        servers.append(CarlaServer(parts[0], port, tm))
    if not servers:
        raise UserInputError(f"{flag} is empty; allowed: {FORMAT}")
    seen = [(s.host, s.port) for s in servers]
    dup = next((k for k in seen if seen.count(k) > 1), None)
    if dup is not None:
        raise UserInputError(f"{flag} names the RPC port {dup[0]}:{dup[1]} twice; each worker needs a server of "
                             "its own")
    # every worker's traffic manager listens on this machine, whichever host its server is on
    tms = [s.tm_port for s in servers]
    shared = next((p for p in tms if tms.count(p) > 1), None)
    if shared is not None:
        twice = ", ".join(str(s) for s in servers if s.tm_port == shared)
        raise UserInputError(f"{flag} gives the traffic-manager port {shared} to two workers ({twice}); traffic "
                             "managers run on this machine, one per port: give each its own as HOST:PORT:TM_PORT")
    return tuple(servers)


def servers_for_workers(backend: str, servers: tuple[CarlaServer, ...], workers: int,
                        what: str = "--workers") -> list[CarlaServer | None]:
    """The server of each of ``workers`` workers (None: the env's own carla_host/carla_port, or no server).
    Refuses more CARLA workers than servers, with the fix in the message."""
    if backend != "carla":
        return [None] * workers
    if not servers:
        if workers > 1:
            raise UserInputError(f"{what} = {workers} on --backend carla would tick one CARLA server from {workers} "
                                 f"processes (a server takes one synchronous client); start {workers} servers "
                                 f"and name them with --carla-servers {FORMAT}, or use {what} 1")
        return [None]
    if len(servers) == 1 and isinstance(servers[0], NodeServer):
        return [servers[0]] * workers  # one per node, each held as a Ray resource (ray_session checks the count)
    if len(servers) < workers:
        raise UserInputError(f"{what} = {workers} but --carla-servers names {len(servers)} server(s); each worker "
                             f"needs its own: allowed {what} 1..{len(servers)}, or start more servers")
    return list(servers[:workers])
