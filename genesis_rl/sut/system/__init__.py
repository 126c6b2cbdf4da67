"""The system under test: perception (detector + depth localisation) and a following controller.

Data flow per step: SensorFrame (RGB, depth) -> detections -> ego-frame positions -> controller ->
VehicleControl. Users plug in their own system through :func:`load_system` with an import path.
"""

from genesis_rl.sut.system.protocol import (
    Detection,
    EpisodeContext,
    SystemOutput,
    SystemUnderTest,
    load_system,
)

__all__ = ["Detection", "EpisodeContext", "SystemOutput", "SystemUnderTest", "load_system"]
