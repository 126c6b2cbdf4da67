"""Optional system: ultralytics YOLO (the paper's yolov5s) with weights the user supplies, behind the same
depth localisation and following controller as the built-in system.

Install with ``pip install -e .[yolo]``. Nothing is downloaded at run time: the weights file must exist
locally (ultralytics would otherwise fetch it from the internet), and ultralytics' online checks are
switched off before it is imported.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.threads import pinned_threads
from genesis_rl.core.trust import check_pickle_file
from genesis_rl.sim.interface import SensorFrame
from genesis_rl.sut.system.builtin import PerceptionDrivenSystem
from genesis_rl.sut.system.controller import ControllerConfig


def _gl_started() -> bool:
    """Whether this process has created the lite renderer's OpenGL pipe (and so loaded Mesa)."""
    render = sys.modules.get("genesis_rl.sim.lite.render.panda_renderer")  # not imported: no renderer yet
    return render is not None and render.gl_pipe_created()


#: COCO class ids of vehicles: car, motorcycle, bus, truck
COCO_VEHICLE_CLASSES = (2, 3, 5, 7)


def import_ultralytics():  # noqa: ANN201
    # ultralytics reads this as offline only when it is the string "true" (any case): "1" is not enough
    os.environ.setdefault("YOLO_OFFLINE", "true")  # no update checks, no asset downloads
    try:
        import ultralytics
    except ImportError:
        raise UserInputError(
            "the yolo system needs the optional 'ultralytics' package: pip install -e '.[yolo]' "
            "(then pass --weights PATH to a local YOLO .pt file, e.g. the paper's yolov5s.pt)"
        ) from None
    return ultralytics


class YoloSystem(PerceptionDrivenSystem):
    """YOLO boxes of COCO vehicle classes (score >= ``score_threshold``) -> depth -> controller."""

    def __init__(self, weights: str | None = None, score_threshold: float = 0.25, image_size: int = 640,
                 controller: ControllerConfig | dict[str, Any] | None = None) -> None:
        super().__init__(controller)
        if not weights:
            raise UserInputError("the yolo system needs --weights PATH to a local YOLO .pt file "
                                 "(nothing is downloaded)")
        path = Path(weights)
        if not path.is_file():
            raise UserInputError(f"YOLO weights file '{path}' does not exist (nothing is downloaded at run time)")
        check_pickle_file(path, "YOLO weights file")  # a .pt file is a pickle: only one the user names
        ultralytics = import_ultralytics()
        try:
            self.model = ultralytics.YOLO(str(path))
        except Exception as err:  # noqa: BLE001
            raise UserInputError(f"YOLO weights file '{path}' cannot be loaded: {err}") from None
        self.weights_path = path
        self.score_threshold = float(score_threshold)
        self.image_size = int(image_size)
        self._warm_up()

    def _warm_up(self) -> None:
        """Predict once on a blank frame now, before any simulator renders.

        ultralytics imports torchvision on its first prediction, and through it (with CUDA builds of torch)
        triton, whose own LLVM crashes the process with a segmentation fault when Mesa's llvmpipe, which
        the lite renderer runs on, was loaded first. Every genesis-rl command creates the system before
        the simulator; a script that does it the other way round gets this error instead of the crash.
        """
        if _gl_started() and importlib.util.find_spec("triton") is not None and "triton" not in sys.modules:
            raise UserInputError(
                "create the yolo system before the first lite simulation in this process: its first prediction "
                "imports triton, which crashes once the renderer's OpenGL (Mesa llvmpipe) is loaded"
            )
        self._boxes(SensorFrame(step=0, rgb=np.zeros((64, 64, 3), np.uint8),
                                depth=np.zeros((64, 64), np.float32), boxes=[]))

    def _boxes(self, frame: SensorFrame) -> np.ndarray:
        with pinned_threads():  # the same floats in every process (core.threads)
            result = self.model.predict(frame.rgb[..., ::-1], imgsz=self.image_size, conf=self.score_threshold,
                                        classes=list(COCO_VEHICLE_CLASSES), verbose=False)[0]
        boxes = result.boxes
        if boxes is None or len(boxes) == 0:
            return np.zeros((0, 5), np.float32)
        xyxy = boxes.xyxy.cpu().numpy().astype(np.float32)
        conf = boxes.conf.cpu().numpy().astype(np.float32)[:, None]
        return np.hstack([xyxy, conf])

    def identity(self) -> dict[str, Any]:
        from genesis_rl.core.files.hashing import file_sha256

        return {**super().identity(), "weights": str(self.weights_path),
                "weights_sha256": file_sha256(self.weights_path), "score_threshold": self.score_threshold}
