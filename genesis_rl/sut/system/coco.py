"""The real-photo system: a detector that learned cars from COCO photographs (darknet yolov3-tiny) behind the
built-in depth localisation and following controller.

The paper's system under test is of this kind (a COCO YOLOv5s behind BehaviorAgent). Its weights come from
the model store, installed once by ``genesis-rl models install coco``; nothing is downloaded at run time.
``weights`` names another folder holding ``yolov3-tiny.cfg``, ``yolov3-tiny.weights`` and ``coco.names``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from genesis_rl.sim.interface import SensorFrame
from genesis_rl.sut.perception.coco_detector import CocoDetector
from genesis_rl.sut.system.builtin import PerceptionDrivenSystem
from genesis_rl.sut.system.controller import ControllerConfig


class CocoSystem(PerceptionDrivenSystem):
    """COCO vehicle boxes (car, bus, truck; score >= ``score_threshold``) -> depth -> controller."""

    def __init__(self, weights: str | None = None, score_threshold: float = 0.25, image_size: int = 416,
                 controller: ControllerConfig | dict[str, Any] | None = None) -> None:
        super().__init__(controller)
        self.detector = CocoDetector(weights, score_threshold=score_threshold, image_size=image_size)

    def _boxes(self, frame: SensorFrame) -> np.ndarray:
        return self.detector.detect(frame.rgb)

    def identity(self) -> dict[str, Any]:
        return {**super().identity(), "detector": self.detector.name, "weights": str(self.detector.weights_path),
                "weights_sha256": self.detector.weights_sha256, "score_threshold": self.detector.score_threshold,
                "image_size": self.detector.image_size}
