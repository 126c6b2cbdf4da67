"""The simulator interface every backend implements (``lite`` embedded, ``carla`` for a real server)."""

from genesis_rl.sim.interface import (
    ActorState,
    Backend,
    CameraConfig,
    Collision,
    ConnectionSettings,
    GroundTruthBox,
    LeadInfo,
    SensorFrame,
    Simulation,
    TickResult,
    VehicleControl,
)

__all__ = [
    "ActorState",
    "Backend",
    "CameraConfig",
    "Collision",
    "ConnectionSettings",
    "GroundTruthBox",
    "LeadInfo",
    "SensorFrame",
    "Simulation",
    "TickResult",
    "VehicleControl",
]
