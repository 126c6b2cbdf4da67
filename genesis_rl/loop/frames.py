"""Camera frames annotated with true (green) and detected (orange) boxes and a telemetry strip; GIFs."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from genesis_rl.core.files.io_utils import atomic_write
from genesis_rl.world.step_record import StepRecord

GT_COLOR = (60, 220, 60)
DET_COLOR = (255, 150, 0)
HIT_COLOR = (230, 30, 30)


def annotate_frame(rgb: np.ndarray, record: StepRecord, scale: int = 1) -> np.ndarray:
    """Upscaled frame with ground-truth boxes (thin green), detections (orange, with score) and a strip
    below: time, ego speed, true/perceived lead gap, controller state, IoU. A red border marks a collision."""
    h, w = rgb.shape[:2]
    img = cv2.resize(rgb, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)
    for b in record.perception.gt_boxes:
        x0, y0, x1, y1 = (int(v * scale) for v in b.box_xyxy)
        cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), GT_COLOR, 1)
    for d in record.perception.detections:
        x0, y0, x1, y1 = (int(round(v * scale)) for v in d.box_xyxy)
        cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), DET_COLOR, 2)
        if x1 - x0 >= 28 * scale:  # label only boxes wide enough to carry it
            cv2.putText(img, f"{d.score:.2f}", (x0, max(y0 - 3, 10)), cv2.FONT_HERSHEY_PLAIN, 0.9,
                        DET_COLOR, 1, cv2.LINE_AA)
    if record.collision.collided:
        cv2.rectangle(img, (0, 0), (img.shape[1] - 1, img.shape[0] - 1), HIT_COLOR, 6)

    def fmt(v: float) -> str:
        return "-" if v is None or not np.isfinite(v) else f"{v:5.1f}"

    e, lead, k = record.ego, record.lead, record.knobs
    lines = [
        f"t {record.time_s:5.2f}s v {e.speed:4.1f}m/s {e.status}",
        f"lead gap {fmt(lead.true_distance)} seen {fmt(lead.perceived_distance)} IoU {record.iou:.2f}",
        f"thr {e.throttle:.2f} brk {e.brake:.2f} fog {k.get('fog_density', 0):.0f}"
        f" rain {k.get('precipitation', 0):.0f} sun {k.get('sun_altitude_angle', 0):.0f}",
    ]
    font_scale = 0.8 * img.shape[1] / 320.0
    pitch = int(round(12 * img.shape[1] / 320.0))
    strip = np.full((pitch * len(lines) + 6, img.shape[1], 3), 20, np.uint8)
    for row, text in enumerate(lines):
        cv2.putText(strip, text, (4, pitch * (row + 1)), cv2.FONT_HERSHEY_PLAIN, font_scale, (235, 235, 235), 1,
                    cv2.LINE_AA)
    return np.vstack([img, strip])


def write_gif(path: Path, frames: list[np.ndarray], fps: float) -> None:
    """An endlessly looping GIF (one shared adaptive palette per frame), written atomically."""
    # no dithering: sensor noise already dithers, and dithered noise does not compress
    images = [Image.fromarray(f).quantize(colors=96, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
              for f in frames]

    def write(p: Path) -> None:
        images[0].save(p, format="GIF", save_all=True, append_images=images[1:], duration=round(1000.0 / fps),
                       loop=0, optimize=True)

    atomic_write(Path(path), write)
