"""The system-under-test protocol and the loader for user systems given by import path.

A system is anything with ``reset(context)`` and ``step(frame, ego, time_s) -> SystemOutput`` (a
:class:`typing.Protocol`, so users need not inherit from us). It returns its control *and* the detections
it acted on: the reward needs them for the IoU, and the failure analysis for the detection timeline.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.plugins import load_class
from genesis_rl.sim.interface import ActorState, CameraConfig, SensorFrame, VehicleControl
from genesis_rl.world.step_record import RecordedDetection


@dataclass(frozen=True)
class Detection:
    """One detected vehicle: pixel box, confidence, and (when localised) its nearest visible point in the
    ego frame (x forward, y left, z up; metres from the ego's centre on the ground)."""

    x0: float
    y0: float
    x1: float
    y1: float
    score: float
    position: tuple[float, float, float] | None = None

    @property
    def xyxy(self) -> tuple[float, float, float, float]:
        return (self.x0, self.y0, self.x1, self.y1)

    def recorded(self) -> RecordedDetection:
        """The detection as step records and files keep it (box to 0.1 px, score to 4 decimals, position to mm)."""
        x0, y0, x1, y1 = (round(v, 1) for v in self.xyxy)
        p = self.position
        return RecordedDetection((x0, y0, x1, y1), round(self.score, 4),
                                 None if p is None else (round(p[0], 3), round(p[1], 3), round(p[2], 3)))

    def as_dict(self) -> dict[str, Any]:
        return self.recorded().to_row()


@dataclass(frozen=True)
class EpisodeContext:
    """What a system may know about an episode before it starts: the map (for its route and traffic
    lights, as CARLA's BehaviorAgent reads the map), its own start, the camera, the time step and a seed for
    its own random choices (e.g. turns at junctions). Never the other vehicles' states."""

    backend: str
    map_name: str
    road_map: Any
    camera: CameraConfig
    dt: float
    seed: int
    ego_lane: int = -1
    ego_s: float = 0.0
    ego_next_lane: int = -1
    signal_time_offset: float = 0.0
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SystemOutput:
    """A system's answer for one step. ``lead_distance`` is the bumper gap to the vehicle it is following
    as it perceives it (None: it perceives nothing in its path); ``status`` is a short free-text state for
    telemetry (e.g. 'cruise', 'follow', 'red_light', 'emergency')."""

    control: VehicleControl
    detections: list[Detection]
    lead_distance: float | None = None
    status: str = ""


@runtime_checkable
class SystemUnderTest(Protocol):
    """The protocol a system under test implements."""

    def reset(self, context: EpisodeContext) -> None:
        """Start an episode."""

    def step(self, frame: SensorFrame, ego: ActorState, time_s: float) -> SystemOutput:
        """Perceive ``frame``, decide, and return the control for the next tick."""

    def identity(self) -> dict[str, Any]:
        """Class name, version and weights hash: recorded with every edge case so it can be replayed."""


REQUIRED_METHODS = ("reset", "step", "identity")
BUILTIN_SYSTEMS = {
    "builtin": "genesis_rl.sut.system.builtin:BuiltinSystem",
    "blind": "genesis_rl.sut.system.builtin:BlindSystem",
    "oracle": "genesis_rl.sut.system.builtin:OracleSystem",
    "yolo": "genesis_rl.sut.system.yolo_adapter:YoloSystem",
    "coco": "genesis_rl.sut.system.coco:CocoSystem",
    "latency": "genesis_rl.sut.system.latency:LatencySystem",
    "stall": "genesis_rl.sut.system.stall:StallSystem",
    "adaptive": "genesis_rl.sut.system.adaptive:AdaptiveSystem",
}
#: built-in systems that read a weights file (or, for coco, a model folder) given by --weights
WEIGHTED_SYSTEMS = ("builtin", "yolo", "coco", "latency", "adaptive", "stall")


def load_system(spec: str, **kwargs: Any) -> SystemUnderTest:
    """Instantiate a system from ``package.module:Class`` or a built-in name (``BUILTIN_SYSTEMS``).

    Errors name what is wrong: a malformed path, a module that does not import, a missing class, a class
    that lacks the protocol's methods, or a constructor that fails.
    """
    cls = load_class(spec, "system", BUILTIN_SYSTEMS, methods=REQUIRED_METHODS,
                     protocol="genesis_rl.sut.system.protocol")
    try:
        return cls(**kwargs)
    except UserInputError:
        raise
    except Exception as err:  # noqa: BLE001
        raise UserInputError(f"system '{spec}': constructing {cls.__name__} failed: {err}") from None
