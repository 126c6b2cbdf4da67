"""A backend from outside the package: the lite simulator, with every tick written to a log.

Named by its import path (``ticklog_backend:TickLogBackend``, with this folder on ``sys.path``) in
``EnvConfig(backend=...)`` or ``--backend``; nothing in genesis_rl names it. As a subclass of LiteBackend it
drives lite catalogs (``catalog_kind`` is inherited), so scenes are generated and checked as lite's.
"""

from __future__ import annotations

from dataclasses import dataclass

from genesis_rl.sim.interface import CameraConfig, TickResult
from genesis_rl.sim.lite.backend import LiteBackend, LiteSimulation
from genesis_rl.world.knobs import Weather
from genesis_rl.world.scenes.catalog import Scene


@dataclass(frozen=True)
class Tick:
    """One tick as the backend saw it: the step it reached, the ego's speed after it, its collisions."""

    scene: int
    step: int
    ego_speed: float  # [m/s]
    collisions: int


class TickLogSimulation(LiteSimulation):
    def __init__(self, log: list[Tick], *args: object) -> None:
        super().__init__(*args)  # type: ignore[arg-type]
        self._log = log

    def tick(self) -> TickResult:
        result = super().tick()
        self._log.append(Tick(self.scene.index, result.step, self.ego().speed, len(result.collisions)))
        return result


class TickLogBackend(LiteBackend):
    """Lite, logging each tick in ``ticks`` (one list across the backend's episodes)."""

    name = "ticklog"

    def __init__(self) -> None:
        super().__init__()
        self.ticks: list[Tick] = []

    def create_simulation(self, scene: Scene, *, seed: int, weather: Weather | None = None,
                          camera: CameraConfig | None = None, render: bool = True) -> TickLogSimulation:
        return TickLogSimulation(self.ticks, self, scene, seed, weather or Weather.default(),
                                 camera or CameraConfig(), render)
