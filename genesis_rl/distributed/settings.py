"""Where parallel work runs: the executor (local processes or Ray), how many workers, which Ray cluster and
which CARLA server each worker drives. Campaigns (``--workers``) and training (``--envs``) share it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.distributed.servers import CarlaServer

EXECUTORS = ("local", "ray")


@dataclass(frozen=True)
class ExecutorSettings:
    """How to run parallel work: a campaign's episodes (``--workers``) or a training run's envs (``--envs``)."""

    kind: str = "local"  # local or ray
    workers: int = 1  # processes (local) or Ray actors, each one episode at a time
    ray_address: str | None = None  # None: a local Ray instance; HOST:PORT, ray://HOST:PORT or auto
    servers: tuple[CarlaServer | None, ...] = ()  # worker i's CARLA server (servers_for_workers)
    what: str = "--workers"  # the flag that set ``workers``, for messages

    def __post_init__(self) -> None:
        if self.kind not in EXECUTORS:
            raise UserInputError(f"--executor = '{self.kind}'; allowed: {', '.join(EXECUTORS)}")
        if self.workers < 1:
            raise UserInputError(f"{self.what} = {self.workers} must be >= 1")
        if self.ray_address is not None and self.kind != "ray":
            raise UserInputError("--ray-address needs --executor ray")
        if self.kind != "ray" and any(s is not None and s.ray_resources() for s in self.servers):
            raise UserInputError("--carla-servers ray: the servers are Ray resources; add --executor ray (or name "
                                 "them as HOST:PORT,... for local processes)")

    def preflight(self) -> None:
        """Before any folder is touched: Ray installed and its address answering (with ``kind`` ray)."""
        if self.kind == "ray":
            from genesis_rl.distributed.ray_cluster import check_reachable, require_ray

            require_ray()
            if self.ray_address:
                check_reachable(self.ray_address)

    def _server_at(self, i: int) -> CarlaServer | None:
        return self.servers[i] if i < len(self.servers) else None

    def server(self, i: int) -> dict[str, Any]:
        s = self._server_at(i)
        return s.env_settings() if s is not None else {}

    def ray_resources(self, i: int) -> dict[str, float]:
        """The custom Ray resources worker i holds (its node's CARLA server with ``--carla-servers ray``)."""
        s = self._server_at(i)
        return s.ray_resources() if s is not None else {}


