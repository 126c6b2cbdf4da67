"""Train the built-in vehicle detector on lite renders of TYPICAL conditions (``genesis-rl detector train``).

Recipe (the defaults of :class:`DetectorTrainConfig` are the shipped weights' recipe): training frames
from ``train_scenes`` scenes of an ``urban`` catalog (seed ``train_catalog_seed``), validation frames from
other scenes (``val_catalog_seed``), both in the ``typical`` weather distribution only (daylight, fog <= 10,
rain <= 20), as a real perception team's data would be (``condition``: the zoo's dusk-blind detector learns
``day_night``). CenterNet losses: penalty-reduced focal loss on the
heatmap, L1 on log box size and centre offset. Light photometric augmentation only (flip, brightness,
contrast, sensor noise): no fog, rain or night, on purpose. The score threshold is the one that maximises F1
on the validation frames under the evaluation protocol (``evaluate.py``).
"""

from __future__ import annotations

import dataclasses
import math
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json, ensure_writable
from genesis_rl.sut.perception.dataset import DetectionDataset, render_dataset
from genesis_rl.sut.perception.detector import CHECKPOINT_FORMAT, CHECKPOINT_VERSION
from genesis_rl.sut.perception.evaluate import EvalProtocol, MatchCounts, score_dataset

WEIGHTS_NAME = "vehicle_detector.pt"
METRICS_NAME = "vehicle_detector.json"
THRESHOLD_GRID = tuple(round(t, 2) for t in np.arange(0.10, 0.80, 0.05))


@dataclass(frozen=True)
class DetectorTrainConfig:
    """Everything that defines a trained detector. Units next to values."""

    map: str = "urban"
    train_scenes: int = 900  # scenes of the training catalog
    frames_per_scene: int = 4  # captured traffic states per scene (a new weather each)
    val_scenes: int = 120  # held-out scenes (another catalog seed)
    train_catalog_seed: int = 100
    val_catalog_seed: int = 101
    seed: int = 0  # sim seed, weather draws, init, shuffling, augmentation
    #: the weather distribution of the training and validation frames (``dataset.CONDITIONS``): ``typical`` for
    #: the shipped weights; ``day_night`` for the zoo's dusk-blind detector (docs/zoo.md)
    condition: str = "typical"
    epochs: int = 20  # the loss was still falling at 12 (0.1.0 weights); 20 lifted clear-day recall
    batch_size: int = 32
    lr: float = 2e-3  # Adam, cosine decay to 2 % after a one-epoch linear warm-up
    weight_decay: float = 1e-4
    size_weight: float = 1.0  # L1 on log(w), log(h)
    offset_weight: float = 1.0  # L1 on the sub-cell centre offset
    min_train_height: float = 5.0  # [px] smaller (or mostly hidden) vehicles are ignore regions in the loss
    min_train_width: float = 4.0  # [px]
    min_train_visible: float = 0.2
    channels: tuple[int, ...] = (16, 24, 32, 48, 64)
    fpn_channels: int = 32
    input_width: int = 320  # [px] also the render size
    input_height: int = 240  # [px]
    flip: bool = True
    brightness: float = 0.12  # additive jitter, +- (0..1 pixel scale)
    contrast: float = 0.2  # multiplicative jitter, 1 +- this
    noise_sigma: float = 0.02  # max std of added gaussian noise (0..1 scale)
    threads: int = 2  # torch.set_num_threads
    cache_data: bool = True  # keep the rendered datasets (train_data.npz, val_data.npz) in out_dir

    def __post_init__(self) -> None:
        for name in ("train_scenes", "frames_per_scene", "val_scenes", "epochs", "batch_size", "threads"):
            if int(getattr(self, name)) < 1:
                raise UserInputError(f"detector train: {name} must be >= 1, got {getattr(self, name)}")
        if self.train_catalog_seed == self.val_catalog_seed:
            raise UserInputError("detector train: val_catalog_seed must differ from train_catalog_seed "
                                 "(validation uses other scenes)")
        from genesis_rl.sut.perception.dataset import check_conditions

        check_conditions([self.condition], "detector train: condition")
        if not self.lr > 0:
            raise UserInputError(f"detector train: lr must be > 0, got {self.lr}")

    def model_config(self):  # noqa: ANN201
        from genesis_rl.sut.perception.model import DetectorModelConfig

        try:
            return DetectorModelConfig(tuple(self.channels), self.fpn_channels, self.input_width, self.input_height)
        except ValueError as e:
            raise UserInputError(f"detector train: {e}") from None

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["channels"] = list(self.channels)
        return d


# ---------------------------------------------------------------------------------------------- data
def _data(cfg: DetectorTrainConfig, out_dir: Path, split: str, progress: bool,
          backend=None) -> DetectionDataset:  # noqa: ANN001
    from genesis_rl.sim.interface import CameraConfig

    n = cfg.train_scenes if split == "train" else cfg.val_scenes
    cat_seed = cfg.train_catalog_seed if split == "train" else cfg.val_catalog_seed
    want = {"map": cfg.map, "condition": cfg.condition, "n_scenes": n, "frames_per_scene": cfg.frames_per_scene,
            "catalog_seed": cat_seed, "seed": cfg.seed, "width": cfg.input_width, "height": cfg.input_height}
    path = out_dir / f"{split}_data.npz"
    if cfg.cache_data and path.is_file():
        try:
            data = DetectionDataset.load(path)
            if all(data.meta.get(k) == v for k, v in want.items()):
                return data
        except UserInputError:
            pass
    data = render_dataset(cfg.map, n, cfg.frames_per_scene, cat_seed, cfg.seed, cfg.condition,
                          camera=CameraConfig(cfg.input_width, cfg.input_height), progress=progress,
                          backend=backend)
    if cfg.cache_data:
        data.save(path)
    return data


def _split_boxes(rows: np.ndarray, cfg: DetectorTrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """Training positives and ignore regions of one frame's ground truth rows."""
    w, h = rows[:, 3] - rows[:, 1], rows[:, 4] - rows[:, 2]
    pos = (h >= cfg.min_train_height) & (w >= cfg.min_train_width) & (rows[:, 6] >= cfg.min_train_visible)
    return rows[pos, 1:5], rows[~pos, 1:5]


def training_batch(data: DetectionDataset, idx: np.ndarray, cfg: DetectorTrainConfig, rng: np.random.Generator | None):
    """Images (B, 3, H, W) float 0..1 (augmented when ``rng``) and stacked targets."""
    import torch

    from genesis_rl.sut.perception.model import encode_targets, stack_targets

    imgs = data.images[idx]
    stride = 4
    oh, ow = cfg.input_height // stride, cfg.input_width // stride
    targets = []
    flips = rng.random(len(idx)) < 0.5 if (rng is not None and cfg.flip) else np.zeros(len(idx), bool)
    out = np.empty_like(imgs)
    for k, i in enumerate(idx):
        pos, ign = _split_boxes(data.frame_boxes(int(i)), cfg)
        if flips[k]:
            out[k] = imgs[k, :, ::-1]
            W = cfg.input_width
            pos = np.stack([W - pos[:, 2], pos[:, 1], W - pos[:, 0], pos[:, 3]], 1) if len(pos) else pos
            ign = np.stack([W - ign[:, 2], ign[:, 1], W - ign[:, 0], ign[:, 3]], 1) if len(ign) else ign
        else:
            out[k] = imgs[k]
        targets.append(encode_targets(pos, oh, ow, stride, ign))
    x = torch.from_numpy(out).permute(0, 3, 1, 2).float().div_(255.0)
    if rng is not None:
        b = len(idx)
        c = torch.from_numpy(rng.uniform(1 - cfg.contrast, 1 + cfg.contrast, (b, 1, 1, 1)).astype(np.float32))
        br = torch.from_numpy(rng.uniform(-cfg.brightness, cfg.brightness, (b, 1, 1, 1)).astype(np.float32))
        sig = torch.from_numpy(rng.uniform(0, cfg.noise_sigma, (b, 1, 1, 1)).astype(np.float32))
        mean = x.mean(dim=(1, 2, 3), keepdim=True)
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        x = ((x - mean) * c + mean + br + torch.randn(x.shape, generator=gen) * sig).clamp_(0.0, 1.0)
    return x.contiguous(memory_format=torch.channels_last), stack_targets(targets)


def round_for_json(x: float) -> float | None:
    """Round for JSON; NaN (undefined, e.g. precision without detections) becomes null."""
    return None if not math.isfinite(x) else round(float(x), 4)


def detector_loss(out: dict, t: dict, cfg: DetectorTrainConfig):  # noqa: ANN201
    """CenterNet loss: focal (alpha 2, beta 4) on the heatmap + L1 on size and offset at centre cells."""
    import torch
    import torch.nn.functional as F

    logits = out["heatmap"].float().contiguous()
    gt = t["heatmap"]
    weight = t["hm_weight"]
    pos = gt.eq(1.0).float()
    p = torch.sigmoid(logits)
    log_p, log_1mp = F.logsigmoid(logits), F.logsigmoid(-logits)
    pos_loss = (log_p * (1 - p) ** 2 * pos).sum()
    neg_loss = (log_1mp * p**2 * (1 - gt) ** 4 * (1 - pos) * weight).sum()
    n_pos = pos.sum().clamp(min=1.0)
    focal = -(pos_loss + neg_loss) / n_pos
    mask = t["reg_mask"].unsqueeze(1)
    size = (torch.abs(out["size"] - t["size"]) * mask).sum() / n_pos
    off = (torch.abs(out["offset"] - t["offset"]) * mask).sum() / n_pos
    total = focal + cfg.size_weight * size + cfg.offset_weight * off
    return total, {"focal": float(focal.detach()), "size": float(size.detach()), "offset": float(off.detach())}


def predict_boxes(net, data: DetectionDataset, cfg: DetectorTrainConfig, threshold: float,  # noqa: ANN001
             batch: int = 32) -> list[np.ndarray]:
    import torch

    from genesis_rl.sut.perception.model import decode

    net.eval()
    dets: list[np.ndarray] = []
    with torch.inference_mode():
        for s in range(0, len(data), batch):
            x = torch.from_numpy(data.images[s : s + batch]).permute(0, 3, 1, 2).float().div_(255.0)
            x = x.contiguous(memory_format=torch.channels_last)
            dets.extend(decode(net(x), threshold, 50, 4, image_size=(cfg.input_width, cfg.input_height)))
    return dets


def pick_threshold(dets: list[np.ndarray], data: DetectionDataset,
                   protocol: EvalProtocol | None = None) -> tuple[float, dict[float, MatchCounts]]:
    """The grid threshold with the best F1 on ``data`` (``dets`` decoded at the lowest grid threshold)."""
    by_t = {t: score_dataset([d[d[:, 4] >= t] for d in dets], data, protocol) for t in THRESHOLD_GRID}
    best = max(THRESHOLD_GRID, key=lambda t: (round(by_t[t].f1, 4), t))
    return float(best), by_t


def validation_metrics(net, val: DetectionDataset, cfg: DetectorTrainConfig) -> dict:  # noqa: ANN001
    """Pick the score threshold on ``val`` (best F1) and report precision/recall there and per threshold."""
    dets = predict_boxes(net, val, cfg, THRESHOLD_GRID[0])
    thr, by_t = pick_threshold(dets, val)
    m = by_t[thr]
    return {
        "score_threshold": thr, "precision": round_for_json(m.precision), "recall": round_for_json(m.recall),
        "mean_iou": round_for_json(m.mean_iou), "f1": round_for_json(m.f1), "tp": m.tp, "fp": m.fp, "fn": m.fn,
        "by_threshold": {str(t): {"precision": round_for_json(c.precision), "recall": round_for_json(c.recall)}
                         for t, c in by_t.items()},
        "protocol": dataclasses.asdict(EvalProtocol()),
    }


def train_detector(config: DetectorTrainConfig | None = None, out_dir: str | Path = "out/detector",
                   progress: bool = True, force: bool = False, log=print) -> dict:  # noqa: ANN001
    """Render (or load) the data, train, pick the threshold, write the checkpoint and its JSON; return metrics."""
    import torch

    import genesis_rl
    from genesis_rl.sut.perception.model import VehicleDetectorNet, count_parameters

    cfg = config or DetectorTrainConfig()
    out_dir = Path(out_dir)
    wpath, jpath = out_dir / WEIGHTS_NAME, out_dir / METRICS_NAME
    ensure_writable(wpath, force)
    ensure_writable(jpath, force)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(cfg.threads)
    t_start = time.perf_counter()

    t0 = time.perf_counter()
    from genesis_rl.sim.lite.backend import LiteBackend

    with LiteBackend() as backend:
        train = _data(cfg, out_dir, "train", progress, backend)
        val = _data(cfg, out_dir, "val", progress, backend)
    t_data = time.perf_counter() - t0
    log(f"[detector] data: {len(train)} train frames ({len(train.boxes)} boxes), {len(val)} val frames "
        f"in {t_data:.0f} s")

    ss = np.random.SeedSequence([cfg.seed, 7919])
    init_seed, shuffle_ss = ss.spawn(2)
    torch.manual_seed(int(init_seed.generate_state(1)[0]))
    rng = np.random.default_rng(shuffle_ss)
    mcfg = cfg.model_config()
    # Module.to takes memory_format at run time, but torch's overloads for it omit the keyword
    net = VehicleDetectorNet(mcfg).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = math.ceil(len(train) / cfg.batch_size)
    total_steps = steps_per_epoch * cfg.epochs
    warm = steps_per_epoch

    def lr_at(step: int) -> float:
        if step < warm:
            return cfg.lr * (step + 1) / warm
        t = (step - warm) / max(1, total_steps - warm)
        return cfg.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * t)))

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total_steps, desc="train detector", unit="batch")
    history = []
    step = 0
    t0 = time.perf_counter()
    try:
        for epoch in range(cfg.epochs):
            net.train()
            order = rng.permutation(len(train))
            sums = {"loss": 0.0, "focal": 0.0, "size": 0.0, "offset": 0.0}
            for s in range(0, len(order), cfg.batch_size):
                idx = np.sort(order[s : s + cfg.batch_size])
                x, t = training_batch(train, idx, cfg, rng)
                for g in opt.param_groups:
                    g["lr"] = lr_at(step)
                loss, parts = detector_loss(net(x), t, cfg)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
                opt.step()
                step += 1
                sums["loss"] += loss.item()
                for k, v in parts.items():
                    sums[k] += v
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(epoch=epoch + 1, loss=f"{float(loss):.3f}")
            n = math.ceil(len(order) / cfg.batch_size)
            val_m = score_dataset(predict_boxes(net, val, cfg, 0.3), val)
            rec = {"epoch": epoch + 1, **{k: round(v / n, 4) for k, v in sums.items()},
                   "val_precision@0.3": round_for_json(val_m.precision), "val_recall@0.3": round_for_json(val_m.recall),
                   "elapsed_s": round(time.perf_counter() - t0, 1)}
            history.append(rec)
            log(f"[detector] {rec}")
    finally:
        if bar is not None:
            bar.close()
    t_train = time.perf_counter() - t0

    val_metrics = validation_metrics(net, val, cfg)
    thr = val_metrics["score_threshold"]
    log(f"[detector] validation at threshold {thr}: precision {val_metrics['precision']} "
        f"recall {val_metrics['recall']}")

    net.eval()
    state = {k: v.detach().to(torch.float32).contiguous().clone() if v.is_floating_point() else v.clone()
             for k, v in net.state_dict().items()}
    ckpt = {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "model_config": mcfg.as_dict(),
        "state_dict": state, "score_threshold": float(thr),
        "metadata": {"genesis_rl_version": genesis_rl.__version__, "train_config": cfg.as_dict()},
    }
    atomic_write(wpath, lambda p: torch.save(ckpt, p))
    metrics = {
        "format": CHECKPOINT_FORMAT, "weights": WEIGHTS_NAME, "genesis_rl_version": genesis_rl.__version__,
        "torch_version": torch.__version__, "score_threshold": float(thr), "model_config": mcfg.as_dict(),
        "parameters": count_parameters(net), "train_config": cfg.as_dict(),
        "data": {"train_frames": len(train), "train_boxes": len(train.boxes), "val_frames": len(val),
                 "val_boxes": len(val.boxes), "map": cfg.map, "condition": cfg.condition,
                 "train_catalog_seed": cfg.train_catalog_seed, "val_catalog_seed": cfg.val_catalog_seed,
                 "seed": cfg.seed},
        "timing_s": {"data": round(t_data, 1), "train": round(t_train, 1),
                     "total": round(time.perf_counter() - t_start, 1)},
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip() + f", {__import__('os').cpu_count()}"
                   f" CPUs, {cfg.threads} torch threads",
        "validation": val_metrics, "history": history,
    }
    atomic_write_json(jpath, metrics, indent=2)
    return metrics
