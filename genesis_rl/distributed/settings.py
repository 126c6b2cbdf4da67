"""Where parallel work runs: the executor (local processes or Ray), how many workers, which Ray cluster and
which CARLA server each worker drives. Campaigns (``--workers``) and training (``--envs``) share it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from genesis_rl.distributed.servers import CarlaServer
from genesis_rl.errors import UserInputError

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

    def preflight(self) -> None:
        """Before any folder is touched: Ray installed and its address answering (with ``kind`` ray)."""
        if self.kind == "ray":
            from genesis_rl.distributed.ray_cluster import check_reachable, require_ray

            require_ray()
            if self.ray_address:
                check_reachable(self.ray_address)

    def server(self, i: int) -> dict[str, Any]:
        s = self.servers[i] if i < len(self.servers) else None
        return s.env_settings() if s is not None else {}


