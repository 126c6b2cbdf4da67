"""Detector evaluation per (map, weather condition), and its report.

Protocol
--------
* Frames: for each map, ``ceil(frames_per_condition / frames_per_scene)`` scenes of a catalog generated
  with a seed that neither the training nor the validation set used (:data:`EVAL_CATALOG_SEEDS`; the
  highway map is never trained on at all). Each scene runs its traffic a random number of steps and
  captures ``frames_per_scene`` states some steps apart; every state is rendered in every condition, with a
  weather drawn from the condition's sampler (``perception.dataset.CONDITIONS``), so conditions are
  compared on the same traffic.
* Which ground truth counts: a vehicle is *counted* when its distance (nearest visible point, metres
  along the optical axis) is <= 40 m, at least 30 % of its projected box is not hidden by other vehicles
  (``visible_fraction >= 0.3``) and its visible box is at least 8 px tall. At 320x240 with a 90 deg lens
  (focal 160 px) a 1.5 m tall car is 8 px tall at 30 m and a truck at ~40 m: smaller boxes carry too few
  pixels to call a miss a failure of the detector, and mostly hidden vehicles are ambiguous to label.
  Every other ground-truth vehicle is an *ignore* region.
* Matching: detections, best score first, each take the unmatched counted vehicle with the highest IoU
  if that IoU is >= 0.5 (true positive). A detection that does not match a counted vehicle but lies mostly
  inside an ignore region (intersection over the detection's own area >= 0.5, the Caltech-pedestrian rule
  for "don't care" regions, which also covers a box drawn around the whole of a mostly hidden vehicle whose
  ground-truth box is only its visible part) is neither a true nor a false positive; any other detection is
  a false positive (a second detection of a matched vehicle included). Counted vehicles left unmatched are
  misses.
* Figures: precision = TP / (TP + FP) (undefined, shown as "-", when the detector reports nothing),
  recall = TP / counted, mean IoU over the matched pairs.
"""

from __future__ import annotations

import math
import platform
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json, atomic_write_text, ensure_writable
from genesis_rl.sim.geometry import IN_VIEW_RANGE, MIN_BOX_HEIGHT, MIN_VISIBLE_FRACTION
from genesis_rl.sut.perception.dataset import CONDITIONS, EVAL_CONDITIONS, DetectionDataset, check_conditions
from genesis_rl.sut.perception.model import box_iou

#: catalog seeds of the evaluation scenes (training uses 100, validation 101: see train.py)
EVAL_CATALOG_SEEDS = {"urban": 102, "highway": 103}
DEFAULT_EVAL_SEED = 7


@dataclass(frozen=True)
class EvalProtocol:
    """Which ground-truth vehicles count (see the module docstring)."""

    max_distance: float = IN_VIEW_RANGE  # [m]
    min_visible_fraction: float = MIN_VISIBLE_FRACTION
    min_height: float = float(MIN_BOX_HEIGHT)  # [px] at 320x240 (scaled with the frame height)
    iou_threshold: float = 0.5
    ignore_overlap: float = 0.5  # intersection / detection area with an ignore region that excuses a detection

    def counted(self, gt: np.ndarray, image_height: int = 240) -> np.ndarray:
        """Mask of counted rows of ``gt`` (K, 9) in dataset.BOX_COLUMNS layout."""
        h = gt[:, 4] - gt[:, 2]
        return (
            (gt[:, 5] <= self.max_distance)
            & (gt[:, 6] >= self.min_visible_fraction)
            & (h >= self.min_height * image_height / 240.0)
        )


@dataclass
class MatchCounts:
    tp: int = 0
    fp: int = 0
    fn: int = 0
    ignored: int = 0
    iou_sum: float = 0.0

    def add(self, other: MatchCounts) -> None:
        self.tp += other.tp
        self.fp += other.fp
        self.fn += other.fn
        self.ignored += other.ignored
        self.iou_sum += other.iou_sum

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else float("nan")

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else float("nan")

    @property
    def mean_iou(self) -> float:
        return self.iou_sum / self.tp if self.tp else float("nan")

    @property
    def f1(self) -> float:
        d = 2 * self.tp + self.fp + self.fn
        return 2 * self.tp / d if d else float("nan")


def _overlap_of_first(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)): area of a_i & b_j over the area of a_i."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    a, b = np.asarray(a, np.float64)[:, :4], np.asarray(b, np.float64)[:, :4]
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    area = np.maximum((a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]), 1e-9)
    return w * h / area[:, None]


def match_frame(dets: np.ndarray, gt: np.ndarray, protocol: EvalProtocol | None = None,
                image_height: int = 240) -> MatchCounts:
    """Greedy matching of one frame's detections (N, 5) to its ground truth (K, 9 dataset rows)."""
    p = protocol or EvalProtocol()
    dets = np.asarray(dets, np.float32).reshape(-1, 5)
    gt = np.asarray(gt, np.float32).reshape(-1, 9)
    counted = p.counted(gt, image_height)
    gt_c, gt_i = gt[counted, 1:5], gt[~counted, 1:5]
    m = MatchCounts()
    if len(dets):
        dets = dets[np.argsort(-dets[:, 4], kind="stable")]
    iou_c = box_iou(dets, gt_c)
    ioa_i = _overlap_of_first(dets, gt_i)
    taken = np.zeros(len(gt_c), bool)
    for d in range(len(dets)):
        cand = np.where(taken, -1.0, iou_c[d]) if len(gt_c) else np.zeros(0)
        j = int(np.argmax(cand)) if len(cand) else -1
        if j >= 0 and cand[j] >= p.iou_threshold:
            taken[j] = True
            m.tp += 1
            m.iou_sum += float(cand[j])
        elif len(gt_i) and float(ioa_i[d].max()) >= p.ignore_overlap:
            m.ignored += 1
        else:
            m.fp += 1
    m.fn = int((~taken).sum())
    return m


def score_dataset(detections: Sequence[np.ndarray], data: DetectionDataset,
                  protocol: EvalProtocol | None = None) -> MatchCounts:
    total = MatchCounts()
    h = int(data.images.shape[1])
    for i, d in enumerate(detections):
        total.add(match_frame(d, data.frame_boxes(i), protocol, h))
    return total


def _finite(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 4)


def evaluate_detector(
    detector,  # noqa: ANN001  (any Detector: detect_batch(rgbs) -> list of (N, 5))
    map_names: Sequence[str] = ("urban", "highway"),
    conditions: Sequence[str] = EVAL_CONDITIONS,
    frames_per_condition: int = 200,
    seed: int = DEFAULT_EVAL_SEED,
    frames_per_scene: int = 2,
    protocol: EvalProtocol | None = None,
    progress: bool = True,
    backend=None,  # noqa: ANN001
) -> list[dict]:
    """One row per (map, condition): frames, counted vehicles, TP/FP/FN, precision, recall, mean IoU."""
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.maps import MAP_NAMES
    from genesis_rl.sut.perception.dataset import render_condition_sets

    conditions = check_conditions(conditions, "--conditions")
    bad = [m for m in map_names if m not in MAP_NAMES]
    if bad or not map_names:
        raise UserInputError(f"--maps: unknown map(s) {bad or '(none given)'}; allowed: {', '.join(MAP_NAMES)}")
    if frames_per_condition < 1:
        raise UserInputError(f"--frames-per-condition must be >= 1, got {frames_per_condition}")
    fps = max(1, min(frames_per_scene, frames_per_condition))
    n_scenes = math.ceil(frames_per_condition / fps)
    own = backend is None
    backend = backend or LiteBackend()
    rows: list[dict] = []
    try:
        for map_name in map_names:
            sets = render_condition_sets(map_name, n_scenes, fps, EVAL_CATALOG_SEEDS[map_name], seed, conditions,
                                         backend=backend, progress=progress)
            for c in conditions:
                data = sets[c]
                dets = detector.detect_batch(data.images)
                m = score_dataset(dets, data, protocol)
                rows.append({
                    "map": map_name, "condition": c, "frames": len(data), "counted": m.tp + m.fn,
                    "tp": m.tp, "fp": m.fp, "fn": m.fn, "ignored_detections": m.ignored,
                    "precision": _finite(m.precision), "recall": _finite(m.recall), "mean_iou": _finite(m.mean_iou),
                    "catalog_seed": EVAL_CATALOG_SEEDS[map_name], "seed": int(seed),
                })
    finally:
        if own:
            backend.close()
    return rows


def measure_speed(detector, batch_size: int = 16, batches: int = 10, num_threads: int = 2,  # noqa: ANN001
                  size: tuple[int, int] | None = None) -> dict:
    """Frames/s of ``detector.detect_batch`` on random frames at its input size, ``num_threads`` torch threads."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    pinned = getattr(detector, "num_threads", None)  # a detector that pins its own threads runs at these
    if pinned is not None:
        detector.num_threads = num_threads
    try:
        w, h = size or cast("tuple[int, int]", getattr(detector, "input_size", (320, 240)))
        rng = np.random.default_rng(0)
        frames = rng.integers(0, 256, (batch_size, h, w, 3), dtype=np.uint8)
        detector.detect_batch(frames)  # warm-up
        t0 = time.perf_counter()
        for _ in range(batches):
            detector.detect_batch(frames)
        dt = time.perf_counter() - t0
    finally:
        torch.set_num_threads(old)
        if pinned is not None:
            detector.num_threads = pinned
    return {
        "frames_per_s": round(batch_size * batches / dt, 1), "batch_size": batch_size, "threads": num_threads,
        "input_size": [w, h], "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "cpu_count": __import__("os").cpu_count(), "torch": torch.__version__,
    }


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def detector_report_markdown(rows: Sequence[dict]) -> str:
    lines = [
        "| map | condition | frames | counted | TP | FP | FN | precision | recall | mean IoU |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['map']} | {r['condition']} | {r['frames']} | {r['counted']} | {r['tp']} | {r['fp']} | {r['fn']} "
            f"| {_fmt(r['precision'])} | {_fmt(r['recall'])} | {_fmt(r['mean_iou'])} |"
        )
    return "\n".join(lines) + "\n"


def plot_detector_report(rows: Sequence[dict], path: Path) -> None:
    """Grouped bars: recall and precision per condition, one panel per map."""
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    maps = list(dict.fromkeys(r["map"] for r in rows))
    conds = list(dict.fromkeys(r["condition"] for r in rows))
    fig, axes = plt.subplots(len(maps), 1, figsize=(max(7.0, 0.9 * len(conds) + 2), 3.2 * len(maps)),
                             squeeze=False)
    x = np.arange(len(conds))
    for ax, m in zip(axes[:, 0], maps, strict=True):
        by = {r["condition"]: r for r in rows if r["map"] == m}
        rec = [by[c]["recall"] if c in by and by[c]["recall"] is not None else 0.0 for c in conds]
        pre = [by[c]["precision"] if c in by and by[c]["precision"] is not None else 0.0 for c in conds]
        ax.bar(x - 0.2, rec, 0.4, label="recall", color="#1f77b4")
        ax.bar(x + 0.2, pre, 0.4, label="precision", color="#ff7f0e")
        ax.axhline(0.9, color="0.4", lw=0.8, ls="--")
        ax.set_xticks(x)
        ax.set_xticklabels(conds, rotation=20)
        ax.set_ylim(0, 1.05)
        ax.set_title(f"{m}: vehicles <= 40 m, IoU >= 0.5")
        ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    atomic_write(Path(path), lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)


def write_detector_report(rows: Sequence[dict], out_dir: Path, force: bool = False,
                          extra: dict | None = None) -> dict[str, Path]:
    """Write ``detector_eval.md`` (table), ``detector_eval.png`` (plot) and ``detector_eval.json`` (rows)."""
    out_dir = Path(out_dir)
    paths = {k: out_dir / f"detector_eval.{k}" for k in ("md", "png", "json")}
    for p in paths.values():
        ensure_writable(p, force)
    header = "# Detector evaluation\n\nProtocol: see `genesis_rl/sut/perception/evaluate.py` (docstring).\n\n"
    if extra:
        header += "".join(f"- {k}: {v}\n" for k, v in extra.items()) + "\n"
    atomic_write_text(paths["md"], header + detector_report_markdown(rows))
    plot_detector_report(rows, paths["png"])
    atomic_write_json(paths["json"], {"rows": list(rows), **(extra or {})}, indent=2)
    return paths


__all__ = [
    "CONDITIONS", "EvalProtocol", "MatchCounts", "evaluate_detector", "match_frame", "measure_speed",
    "score_dataset", "write_detector_report",
]
