"""Image-box geometry shared by the simulator, the system, perception and evaluation: box IoU, whether a
ground-truth vehicle is in view, and matching detections to ground truth (the IoU that the reward and the
telemetry use). It sits outside those packages so that none of them imports another for it.

Frame IoU (the paper's reward term exp(-IoU)): every ground-truth vehicle *in view* (nearest visible point
within ``IN_VIEW_RANGE`` metres, at least ``MIN_VISIBLE_FRACTION`` of it unoccluded and at least
``MIN_BOX_HEIGHT`` pixels tall) is matched to the detection that overlaps it most; a missed vehicle scores
0; the frame IoU is the mean over those vehicles. With no vehicle in view the frame IoU is 1 (nothing to
miss), so an agent is not rewarded for pointing the camera at an empty road. False positives do not lower
the IoU (the paper's reward is about missing vehicles); they are counted separately.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from genesis_rl.sim.interface import GroundTruthBox

IN_VIEW_RANGE = 40.0  # [m]
MIN_VISIBLE_FRACTION = 0.3
MIN_BOX_HEIGHT = 8  # [px]


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of boxes a (N, 4) and b (M, 4), x0 y0 x1 y1."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    ix0 = np.maximum(a[:, None, 0], b[None, :, 0])
    iy0 = np.maximum(a[:, None, 1], b[None, :, 1])
    ix1 = np.minimum(a[:, None, 2], b[None, :, 2])
    iy1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(ix1 - ix0, 0, None) * np.clip(iy1 - iy0, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-9), 0.0)


def in_view_values(distance: float, visible_fraction: float, height_px: float) -> bool:
    """The in-view criteria on plain numbers (telemetry rows hold boxes as dicts)."""
    return distance <= IN_VIEW_RANGE and visible_fraction >= MIN_VISIBLE_FRACTION and height_px >= MIN_BOX_HEIGHT


def in_view(box: GroundTruthBox) -> bool:
    """Whether a ground-truth vehicle counts for the IoU and the detector's recall."""
    return in_view_values(box.distance, box.visible_fraction, box.y1 - box.y0)


def frame_iou(gt: Sequence[GroundTruthBox], detections_xyxy: np.ndarray) -> tuple[float, dict[int, float]]:
    """Frame IoU (see module docstring) and each in-view vehicle's best IoU by vehicle id."""
    counted = [b for b in gt if in_view(b)]
    if not counted:
        return 1.0, {}
    dets = np.asarray(detections_xyxy, np.float64).reshape(-1, 4)
    if len(dets) == 0:
        return 0.0, {b.vehicle_id: 0.0 for b in counted}
    m = iou_matrix(np.array([b.xyxy for b in counted], np.float64), dets)
    best = m.max(axis=1)
    return float(best.mean()), {b.vehicle_id: float(v) for b, v in zip(counted, best, strict=True)}
