"""``genesis-rl realism``: does a detector that learned cars from photographs believe lite's cars?

A fixed, seeded set of views (both maps, clear noon, the traffic of held-out catalogs seen from the ego at
many distances and angles, at 320x240 and 640x480) is scored by a system's detector:

- **recall of unoccluded vehicles by distance band**: a vehicle counts when at least ``min_visible`` of it
  is visible and it is not cut by the frame's edge; it is *found* when a detection overlaps it with
  IoU >= 0.5 (the detection benchmarks' rule), and, reported beside it, IoU >= 0.3 (a looser box that
  still puts the vehicle where it is, which is what the depth localisation needs);
- **false positives per frame**: detections that overlap no vehicle at all (IoU < 0.1 with every box,
  occluded and distant ones included), so a hit on a half-hidden car is never called false;
- **closed-loop safety**: the system drives ``closed_loop_scenes`` highway scenes at clear noon (the
  ``sunny`` policy of a campaign, 512 steps each); the share without a collision.

Outputs: ``realism.json`` and one contact sheet per map (``realism_sheet_MAP.png``: crops of counted
vehicles at 640x480, green when found, red when missed, by distance band), and the campaign folder
``closed_loop/`` of the closed-loop run (its own report).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.sim.interface import CameraConfig
from genesis_rl.sut.perception.dataset import DetectionDataset, render_condition_sets
from genesis_rl.sut.perception.evaluate import box_iou

#: held-out catalogs (the detector evaluation's: the built-in detector never trained on them)
CATALOG_SEEDS = {"urban": 102, "highway": 103}
BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 40.0))


@dataclass(frozen=True)
class RealismSpec:
    maps: tuple[str, ...] = ("highway", "urban")
    sizes: tuple[tuple[int, int], ...] = ((320, 240), (640, 480))
    scenes: int = 60  # per map
    frames_per_scene: int = 2
    seed: int = 7
    min_visible: float = 0.9
    iou: float = 0.5
    loose_iou: float = 0.3
    closed_loop_scenes: int = 50
    closed_loop_seed: int = 0
    closed_loop_steps: int = 512
    bands: tuple[tuple[float, float], ...] = BANDS


@dataclass
class BandCounts:
    counted: int = 0
    found: int = 0
    found_loose: int = 0

    def as_dict(self) -> dict[str, Any]:
        def share(n: int) -> float | None:
            return round(n / self.counted, 4) if self.counted else None

        return {"counted": self.counted, "found": self.found, "recall": share(self.found),
                "found_loose": self.found_loose, "recall_loose": share(self.found_loose)}


@dataclass
class ViewScore:
    """One (map, size): recall by band, false positives, detector time."""

    map: str
    width: int
    height: int
    frames: int
    bands: dict[str, BandCounts] = field(default_factory=dict)
    false_positives: int = 0
    detect_ms_per_frame: float = 0.0
    hits: list[tuple[int, np.ndarray, bool]] = field(default_factory=list)  # (frame, gt row, found)

    def as_dict(self) -> dict[str, Any]:
        return {"map": self.map, "size": f"{self.width}x{self.height}", "frames": self.frames,
                "recall_by_distance": {k: v.as_dict() for k, v in self.bands.items()},
                "within_20m": _merge(self.bands, 20.0).as_dict(), "within_30m": _merge(self.bands, 30.0).as_dict(),
                "false_positives_per_frame": round(self.false_positives / max(self.frames, 1), 4),
                "detect_ms_per_frame": round(self.detect_ms_per_frame, 1)}


def band_name(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g} m"


def _merge(bands: dict[str, BandCounts], upto: float) -> BandCounts:
    total = BandCounts()
    for name, c in bands.items():
        if float(name.split("-")[1].split()[0]) <= upto:
            total.counted += c.counted
            total.found += c.found
            total.found_loose += c.found_loose
    return total


def render_views(spec: RealismSpec, map_name: str, size: tuple[int, int], progress: bool = False) -> DetectionDataset:
    """The clear-noon views of one map at one size (the same traffic at every size: the same seeds)."""
    return render_condition_sets(map_name, spec.scenes, spec.frames_per_scene, CATALOG_SEEDS[map_name], spec.seed,
                                 ("clear_noon",), camera=CameraConfig(width=size[0], height=size[1]),
                                 progress=progress)["clear_noon"]


def score_views(detect_batch: Callable[[np.ndarray], list[np.ndarray]], data: DetectionDataset, spec: RealismSpec,
                map_name: str) -> ViewScore:
    h, w = data.images.shape[1:3]
    t0 = time.perf_counter()
    detections = detect_batch(data.images)
    elapsed = time.perf_counter() - t0
    score = ViewScore(map_name, int(w), int(h), len(data),
                      bands={band_name(lo, hi): BandCounts() for lo, hi in spec.bands},
                      detect_ms_per_frame=1000 * elapsed / max(len(data), 1))
    for i, dets in enumerate(detections):
        gt = data.frame_boxes(i)
        dets = np.asarray(dets, np.float32).reshape(-1, 5)
        iou_all = box_iou(dets[:, :4], gt[:, 1:5]) if len(dets) and len(gt) else np.zeros((len(dets), len(gt)))
        score.false_positives += int((iou_all.max(1) < 0.1).sum()) if len(gt) else len(dets)
        for k, row in enumerate(gt):
            if row[6] < spec.min_visible or row[7] > 0.5:  # occluded, or cut by the frame's edge
                continue
            best = float(iou_all[:, k].max()) if len(dets) else 0.0
            for lo, hi in spec.bands:
                if lo <= row[5] < hi:
                    c = score.bands[band_name(lo, hi)]
                    c.counted += 1
                    c.found += int(best >= spec.iou)
                    c.found_loose += int(best >= spec.loose_iou)
                    score.hits.append((i, row, best >= spec.iou))
    return score


def contact_sheet(data: DetectionDataset, score: ViewScore, detections: Sequence[np.ndarray] | None, path: Path,
                  per_band: int = 12, tile: int = 96) -> None:
    """Crops of counted vehicles, one row of hits and one of misses per distance band (green / red frame)."""
    import cv2
    from PIL import Image, ImageDraw

    from genesis_rl.core.files.io_utils import atomic_write

    rows: list[np.ndarray] = []
    labels: list[str] = []
    for name in score.bands:
        lo, hi = (float(v) for v in name.split(" ")[0].split("-"))
        for found in (True, False):
            chosen = [(i, r) for i, r, f in score.hits if f == found and lo <= r[5] < hi][:per_band]
            tiles = []
            for i, r in chosen:
                x0, y0, x1, y1 = (float(v) for v in r[1:5])
                cx, cy, half = (x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0, y1 - y0) * 0.75 + 4
                img = data.images[i]
                X0, Y0 = int(max(cx - half, 0)), int(max(cy - half, 0))
                X1, Y1 = int(min(cx + half, img.shape[1])), int(min(cy + half, img.shape[0]))
                crop = cv2.resize(np.ascontiguousarray(img[Y0:Y1, X0:X1]), (tile, tile), interpolation=cv2.INTER_AREA
                                  if Y1 - Y0 > tile else cv2.INTER_LINEAR)
                colour = (40, 200, 60) if found else (220, 40, 40)
                crop = cv2.copyMakeBorder(crop, 3, 3, 3, 3, cv2.BORDER_CONSTANT, value=colour)
                cv2.putText(crop, f"{r[5]:.0f} m", (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
                tiles.append(crop)
            while len(tiles) < per_band:
                tiles.append(np.full((tile + 6, tile + 6, 3), 235, np.uint8))
            rows.append(np.hstack(tiles))
            labels.append(f"{name} {'found' if found else 'missed'}")
    margin = 150
    sheet = np.full((len(rows) * (tile + 6), margin + rows[0].shape[1], 3), 255, np.uint8)
    for k, row in enumerate(rows):
        sheet[k * (tile + 6):(k + 1) * (tile + 6), margin:] = row
    image = Image.fromarray(sheet)
    draw = ImageDraw.Draw(image)
    for k, label in enumerate(labels):
        draw.text((6, k * (tile + 6) + tile // 2 - 6), label, fill=(0, 0, 0))
    atomic_write(path, lambda tmp: image.save(tmp, format="PNG"))


def spec_dict(spec: RealismSpec) -> dict[str, Any]:
    d = asdict(spec)
    d["sizes"] = [f"{w}x{h}" for w, h in spec.sizes]
    d["catalog_seeds"] = {m: CATALOG_SEEDS[m] for m in spec.maps}
    return d
