"""The data a hardening round retrains on: the failure frames an attack found (read back from ``genesis-rl
export``'s YOLO folder, whose ``metadata.jsonl`` keeps each box's distance and visibility), and a slice of the
detector's own training data, rendered again from its recorded recipe, mixed in so that it does not forget."""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.perception.dataset import BOX_COLUMNS, DetectionDataset

#: the detector's input size: frames of another size are resized (their boxes scaled)
FRAME_SIZE = (320, 240)


def export_frames(export: Path, size: tuple[int, int] = FRAME_SIZE) -> DetectionDataset:
    """The frames of one export folder with their labels (positives) and ignore regions, as a detection dataset.

    A label row keeps its ``visible_fraction`` and ``distance``; an ignore region is written with visibility 0,
    so the training rule (``train._split_boxes``) treats it as ignore whatever its size."""
    from PIL import Image

    from genesis_rl.world.knobs import KNOBS, Weather

    meta_path = Path(export) / "metadata.jsonl"
    if not meta_path.is_file():
        raise UserInputError(f"failure export '{export}' has no metadata.jsonl (make it with genesis-rl export)")
    images: list[np.ndarray] = []
    rows: list[list[float]] = []
    weather: list[list[float]] = []
    for line_no, line in enumerate(meta_path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            m = json.loads(line)
            path = Path(export) / m["image"]
            with Image.open(path) as im:
                w, h = im.size
                rgb = np.asarray(im.convert("RGB").resize(size, Image.Resampling.BILINEAR) if (w, h) != size
                                 else im.convert("RGB"), np.uint8)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise UserInputError(f"failure export '{meta_path}' line {line_no}: {err}") from None
        sx, sy = size[0] / w, size[1] / h
        frame = len(images)
        for box, visible in [(b, float(b.get("visible_fraction", 1.0))) for b in m.get("labels", [])] + \
                            [(b, 0.0) for b in m.get("ignore", [])]:
            x0, y0, x1, y1 = (float(v) for v in box["xyxy"])
            rows.append([frame, x0 * sx, y0 * sy, x1 * sx, y1 * sy, float(box.get("distance_m", math.nan)),
                         visible, 0.0, float(box.get("vehicle_id", -1))])
        images.append(rgb)
        knobs = Weather.from_recorded({k: v for k, v in m.get("weather", {}).items() if k in KNOBS})
        weather.append([float(knobs.values[k]) for k in KNOBS])
    if not images:
        return empty_dataset(size)
    return DetectionDataset(np.stack(images), np.asarray(rows, np.float32).reshape(-1, len(BOX_COLUMNS)),
                            np.asarray(weather, np.float32), {"source": str(export), "kind": "failure frames"})


def empty_dataset(size: tuple[int, int] = FRAME_SIZE) -> DetectionDataset:
    from genesis_rl.world.knobs import KNOBS

    return DetectionDataset(np.zeros((0, size[1], size[0], 3), np.uint8), np.zeros((0, len(BOX_COLUMNS)), np.float32),
                            np.zeros((0, len(KNOBS)), np.float32), {})


def concat(parts: Sequence[DetectionDataset]) -> DetectionDataset:
    """The frames of ``parts`` one after another (box rows renumbered)."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return empty_dataset()
    boxes, offset = [], 0
    for p in parts:
        b = p.boxes.copy()
        b[:, 0] += offset
        boxes.append(b)
        offset += len(p)
    return DetectionDataset(np.concatenate([p.images for p in parts]), np.concatenate(boxes),
                            np.concatenate([p.weather for p in parts]), {"parts": [p.meta for p in parts]})


def original_frames(train_config: dict[str, Any], frames: int, cache: Path | None, progress: bool = False,
                    backend: Any = None, split: str = "train") -> DetectionDataset:
    """The first ``frames`` frames of the detector's own training (or, ``split="val"``, validation) data, rendered
    from the recipe its checkpoint records (map, weather condition, catalog seed, seed); kept in ``cache`` (an
    ``.npz``) when given. A cache in a folder that keeps pins (a harden folder's ``pins.json``) is checked
    against its pin before it is reused, and pinned when it is written."""
    from genesis_rl.core.files import pins as pinning
    from genesis_rl.sim.interface import CameraConfig
    from genesis_rl.sut.perception.dataset import render_dataset

    pins = pinning.Pins(cache.parent) if cache is not None and (cache.parent / pinning.NAME).is_file() else None

    fps = int(train_config.get("frames_per_scene", 4))
    seed_key, seed_default = ("train_catalog_seed", 100) if split == "train" else ("val_catalog_seed", 101)
    want = {"map": train_config.get("map", "urban"), "condition": train_config.get("condition", "typical"),
            "catalog_seed": int(train_config.get(seed_key, seed_default)), "seed": int(train_config.get("seed", 0)),
            "frames": int(frames), "frames_per_scene": fps}
    if cache is not None and cache.is_file():
        pinned = pins is not None and pins.check(cache)  # an edited cache is refused, named, before it is trained on
        try:
            data = DetectionDataset.load(cache)
            if data.meta.get("original") == want:
                if pins is not None and not pinned:
                    pins.record(cache)  # a cache of before the pins, as found
                return data
        except UserInputError:
            pass
    n_scenes = max(1, math.ceil(frames / fps))
    size = (int(train_config.get("input_width", FRAME_SIZE[0])), int(train_config.get("input_height", FRAME_SIZE[1])))
    data = render_dataset(want["map"], n_scenes, fps, want["catalog_seed"], want["seed"], want["condition"],
                          camera=CameraConfig(*size), progress=progress, backend=backend)
    data = data.subset(np.arange(min(frames, len(data))))
    data.meta = {**data.meta, "original": want}
    if cache is not None:
        data.save(cache)
        if pins is not None:
            pins.record(cache)
    return data


def dataset_sha256(data: DetectionDataset) -> str:
    """A digest of the pixels and boxes (what a round trained on), for its pin."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(data.images).tobytes())
    h.update(np.ascontiguousarray(data.boxes).tobytes())
    return h.hexdigest()
