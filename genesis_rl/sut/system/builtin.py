"""The built-in system under test: vehicle detector -> depth localisation -> following controller.

``BuiltinSystem`` is the paper's system with our own detector; ``BlindSystem`` sees nothing (to show that
the controller depends on perception); ``OracleSystem`` takes the simulator's ground-truth boxes as its
detections, which separates perception failures from control failures in an analysis.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from genesis_rl import __version__
from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.interface import ActorState, SensorFrame
from genesis_rl.sim.lite.maps.lane_graph import RoadMap
from genesis_rl.sim.route import LaneRoute, PolylineRoute
from genesis_rl.sut.perception.detector import VehicleDetector
from genesis_rl.sut.system.controller import ControllerConfig, FollowingController
from genesis_rl.sut.system.localisation import box_depth, localise
from genesis_rl.sut.system.protocol import Detection, EpisodeContext, SystemOutput


def plan_route(context: EpisodeContext) -> PolylineRoute:
    """The controller's route on the episode's map: a lite ``RoadMap`` (any backend that drives lite catalogs
    hands one over), or the route the backend plans on its own map, from ``context.extras['plan_route']``
    (CARLA's: :func:`genesis_rl.sim.carla.route.route_from_context`). The backend brings its planner, so
    the system depends on no backend."""
    if isinstance(context.road_map, RoadMap):
        rng = np.random.default_rng(np.random.SeedSequence([context.seed, 7]))
        return LaneRoute(context.road_map, context.ego_lane, context.ego_s, context.ego_next_lane, rng)
    planner = context.extras.get("plan_route")
    if planner is None:
        raise UserInputError(f"the built-in controller plans routes on lite maps, or with the backend's planner "
                             f"(EpisodeContext.extras['plan_route']); backend '{context.backend}' gave neither "
                             f"(its map is a {type(context.road_map).__name__})")
    return cast(PolylineRoute, planner(context))


class PerceptionDrivenSystem:
    """Shared loop: boxes from ``_boxes`` -> depth localisation -> controller. Subclasses pick the boxes."""

    def __init__(self, controller: ControllerConfig | dict[str, Any] | None = None) -> None:
        if isinstance(controller, dict):
            try:
                controller = ControllerConfig(**controller)
            except TypeError as err:
                raise ValueError(f"controller settings: {err}") from None
        self.controller = FollowingController(controller)
        self.context: EpisodeContext | None = None

    def reset(self, context: EpisodeContext) -> None:
        self.context = context
        self.controller.reset(plan_route(context), context.dt, context.signal_time_offset)

    def _boxes(self, frame: SensorFrame) -> np.ndarray:
        """(N, 5) x0, y0, x1, y1, score."""
        raise NotImplementedError

    def perceive(self, frame: SensorFrame) -> list[Detection]:
        """This frame's detections, each localised in the ego frame from the depth under its box."""
        assert self.context is not None, "call reset() first"
        cam = self.context.camera
        detections = []
        for x0, y0, x1, y1, score in self._boxes(frame):
            box = (float(x0), float(y0), float(x1), float(y1))
            d = box_depth(frame.depth, box, cam.max_range)
            pos = localise(box, d, cam) if np.isfinite(d) else None
            detections.append(Detection(*box, float(score), pos))
        return detections

    def step(self, frame: SensorFrame, ego: ActorState, time_s: float) -> SystemOutput:
        detections = self.perceive(frame)
        control, gap = self.controller.step(ego, detections, time_s)
        return SystemOutput(control, detections, gap, self.controller.status)

    def identity(self) -> dict[str, Any]:
        return {"class": f"{type(self).__module__}:{type(self).__qualname__}", "version": __version__}


class BuiltinSystem(PerceptionDrivenSystem):
    """Our CNN vehicle detector (weights shipped in the package unless ``weights`` is given)."""

    def __init__(self, weights: str | None = None, score_threshold: float | None = None,
                 controller: ControllerConfig | dict[str, Any] | None = None) -> None:
        super().__init__(controller)
        self.detector = VehicleDetector(weights, score_threshold=score_threshold)

    def _boxes(self, frame: SensorFrame) -> np.ndarray:
        return self.detector.detect(frame.rgb)

    def identity(self) -> dict[str, Any]:
        return {**super().identity(), "weights": str(self.detector.weights_path),
                "weights_sha256": self.detector.weights_sha256,
                "score_threshold": self.detector.score_threshold}


class BlindSystem(PerceptionDrivenSystem):
    """Detects nothing: the controller then drives into whatever stops in front of it."""

    def _boxes(self, frame: SensorFrame) -> np.ndarray:
        return np.zeros((0, 5), np.float32)


class OracleSystem(PerceptionDrivenSystem):
    """Ground-truth boxes as detections (score 1): perfect perception, the same controller."""

    def _boxes(self, frame: SensorFrame) -> np.ndarray:
        if not frame.boxes:
            return np.zeros((0, 5), np.float32)
        return np.array([[*b.xyxy, 1.0] for b in frame.boxes], np.float32)
