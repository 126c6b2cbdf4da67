"""The built-in retrain for the real-photo system (``coco``: darknet yolov3-tiny trained on COCO photographs).

No COCO photograph is at hand offline, so the detector cannot be shown its own training data again. Forgetting is
held off the way learning without forgetting does it without the old data (Li & Hoiem 2016): on lite's clear-day
frames of the campaign's map (training catalog, never the clear-day evaluation's) the new network's objectness and
class outputs are pulled towards the starting weights' (distillation), while those frames' simulator boxes and the
failure frames' boxes train it with YOLOv3's loss (Redmon & Farhadi 2018): each box to the best of the six anchors
by shape, the cell of its centre; sigmoid offsets and log size ratios; objectness; and, since lite's boxes say
"vehicle" and not which COCO class, the most likely vehicle class (car, bus or truck) pushed up. Predictions that
overlap a box or an ignore region by IoU 0.5 are not punished as background (YOLOv3's ignore rule).

The early convolutions stay frozen (``freeze``: the first layers, the stride-2..16 feature extractor): the failures
are a new look of cars, not a new kind of edge. The weights are written as a darknet model folder that
``--system coco --weights FOLDER`` (and darknet itself) loads: ``yolov3-tiny.cfg`` with batch norm folded into the
convolutions' biases, ``yolov3-tiny.weights``, ``coco.names``.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.core.errors import UserInputError

#: positives among lite's boxes: tall enough for a photo detector's stride-16 head, and mostly visible
MIN_HEIGHT = 8.0  # [px of the 320x240 frame]
MIN_VISIBLE = 0.3
IGNORE_IOU = 0.5
WEIGHTS_NAME = "yolov3-tiny.weights"
CFG_NAME = "yolov3-tiny.cfg"


@dataclass(frozen=True)
class DarknetFinetuneConfig:
    """The real-photo detector's fine-tune: a few epochs at a low rate, on every round's failure frames (each seen
    ``failure_repeat`` times an epoch) and ``original_frames`` clear-day lite frames with distillation."""

    epochs: int = 3
    lr: float = 1e-4  # Adam, cosine decay to 2 %
    original_frames: int = 300
    failure_repeat: int = 2
    batch_size: int = 8
    threads: int = 2
    #: weight of the distillation term on the clear-day frames (objectness and class outputs kept close to the
    #: starting weights'); 0 turns it off
    distill: float = 1.0
    #: the first ``freeze`` layers of the cfg are held (yolov3-tiny: 8 = its first four convolutions)
    freeze: int = 8

    def __post_init__(self) -> None:
        for name in ("epochs", "original_frames", "failure_repeat", "batch_size", "threads"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise UserInputError(f"harden finetune.{name} = {value!r}; allowed: an integer >= 1")
        if not isinstance(self.freeze, int) or isinstance(self.freeze, bool) or self.freeze < 0:
            raise UserInputError(f"harden finetune.freeze = {self.freeze!r}; allowed: an integer >= 0")
        if not (isinstance(self.distill, (int, float)) and 0 <= self.distill <= 100):
            raise UserInputError(f"harden finetune.distill = {self.distill!r}; allowed: a number in [0, 100]")
        if not (isinstance(self.lr, (int, float)) and 0 < self.lr <= 0.1):
            raise UserInputError(f"harden finetune.lr = {self.lr!r}; allowed: a number in (0, 0.1]")


# ------------------------------------------------------------------------------------------------ cfg / weights
def folded_cfg(cfg_text: str) -> str:
    """The cfg with ``batch_normalize`` dropped: the network holds batch norm folded into conv biases."""
    return "".join(line for line in cfg_text.splitlines(keepends=True)
                   if not line.replace(" ", "").startswith("batch_normalize="))


def weights_bytes(net: Any) -> bytes:
    """``net``'s convolutions as a darknet ``.weights`` file (version 0.2, no batch norm: bias, then kernel)."""
    header = np.array([0, 2, 0], "<i4").tobytes() + np.array([0], "<i8").tobytes()
    parts = [header]
    for index, kind in enumerate(net.kinds):
        if kind == "convolutional":
            conv = net._conv(index)
            parts.append(conv.bias.detach().numpy().astype("<f4").tobytes())
            parts.append(conv.weight.detach().numpy().astype("<f4").tobytes())
    return b"".join(parts)


# ------------------------------------------------------------------------------------------------------ loss
def _iou_wh(wh: Any, anchors: Any) -> Any:
    """IoU of boxes and anchors by shape alone (both centred): (N, A)."""
    import torch

    inter = torch.minimum(wh[:, None, 0], anchors[None, :, 0]) * torch.minimum(wh[:, None, 1], anchors[None, :, 1])
    return inter / (wh[:, None, 0] * wh[:, None, 1] + anchors[None, :, 0] * anchors[None, :, 1] - inter)


def _iou_xyxy(a: Any, b: Any) -> Any:
    import torch

    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area = (a[:, 2:] - a[:, :2]).prod(-1)[:, None] + (b[:, 2:] - b[:, :2]).prod(-1)[None, :]
    return inter / (area - inter).clamp(min=1e-9)


def yolo_loss(net: Any, raw: list[Any], boxes: list[Any], ignores: list[Any], input_hw: tuple[int, int],
              vehicle_classes: list[int]) -> Any:
    """YOLOv3's loss summed over anchors, averaged over images. ``boxes``/``ignores``: per image (N, 4) x0, y0, x1,
    y1 in input pixels."""
    import torch
    import torch.nn.functional as F

    heads = list(net.heads.values())
    all_anchors = torch.tensor([a for h in heads for a in h.anchors], dtype=torch.float32)
    h_in, w_in = input_hw
    total = torch.zeros(())
    vc = torch.tensor(vehicle_classes)
    offset = 0
    for out, head in zip(raw, heads, strict=True):
        b, _, gh, gw = out.shape
        a = len(head.anchors)
        p = out.view(b, a, 5 + head.classes, gh, gw).permute(0, 1, 3, 4, 2)
        sx, sy = w_in / gw, h_in / gh
        anchors = torch.tensor(head.anchors, dtype=torch.float32)
        with torch.no_grad():  # the decoded boxes, for the ignore rule
            gy, gx = torch.meshgrid(torch.arange(gh), torch.arange(gw), indexing="ij")
            cxy = (torch.sigmoid(p[..., :2]) + torch.stack([gx, gy], -1)) * torch.tensor([sx, sy])
            wh = torch.exp(p[..., 2:4].clamp(max=10.0)) * anchors.view(1, a, 1, 1, 2)
            pred = torch.cat([cxy - wh / 2, cxy + wh / 2], -1)
        obj_target = torch.zeros(b, a, gh, gw)
        noobj = torch.ones(b, a, gh, gw, dtype=torch.bool)
        for i in range(b):
            known = torch.cat([boxes[i], ignores[i]]) if len(ignores[i]) else boxes[i]
            if len(known):
                best = _iou_xyxy(pred[i].reshape(-1, 4), known).max(1).values.view(a, gh, gw)
                noobj[i] &= best < IGNORE_IOU
            gt = boxes[i]
            if not len(gt):
                continue
            bwh = (gt[:, 2:] - gt[:, :2]).clamp(min=1.0)
            bxy = (gt[:, :2] + gt[:, 2:]) / 2
            best_anchor = _iou_wh(bwh, all_anchors).argmax(1) - offset
            for k in torch.nonzero((best_anchor >= 0) & (best_anchor < a)).flatten().tolist():
                j = int(best_anchor[k])
                cx, cy = float(bxy[k, 0]) / sx, float(bxy[k, 1]) / sy
                ci, cj = min(int(cx), gw - 1), min(int(cy), gh - 1)
                cell = p[i, j, cj, ci]
                scale = 2.0 - float(bwh[k, 0] * bwh[k, 1]) / (w_in * h_in)  # small boxes weigh more
                txy = torch.tensor([cx - ci, cy - cj]).clamp(1e-4, 1 - 1e-4)
                twh = torch.log(bwh[k] / anchors[j])
                total = total + scale * (F.binary_cross_entropy_with_logits(cell[:2], txy, reduction="sum")
                                         + 0.5 * ((cell[2:4] - twh) ** 2).sum())
                # lite's boxes say "vehicle": the most likely vehicle class is pushed up
                total = total - F.logsigmoid(cell[5 + vc]).max()
                obj_target[i, j, cj, ci] = 1.0
                noobj[i, j, cj, ci] = False
        obj = p[..., 4]
        positive = obj_target > 0
        total = total + F.binary_cross_entropy_with_logits(obj[positive], obj_target[positive], reduction="sum")
        total = total + F.binary_cross_entropy_with_logits(obj[noobj], obj_target[noobj], reduction="sum")
        offset += a
    return total / max(1, len(raw[0]))


def distillation(net: Any, raw: list[Any], teacher_raw: list[Any], mask: Any) -> Any:
    """On the clear-day frames (``mask``), the KL divergence of each anchor's objectness Bernoulli from the
    teacher's, and of its class outputs weighted by the teacher's objectness: summed, averaged over frames."""
    import torch

    if not bool(mask.any()):
        return torch.zeros(())
    total = torch.zeros(())
    for out, t_out, head in zip(raw, teacher_raw, net.heads.values(), strict=True):
        b, _, gh, gw = out.shape
        a = len(head.anchors)
        p = out[mask].view(-1, a, 5 + head.classes, gh, gw)
        t = torch.sigmoid(t_out[mask].view(-1, a, 5 + head.classes, gh, gw))
        total = total + _kl(p[:, :, 4], t[:, :, 4])
        total = total + _kl(p[:, :, 5:], t[:, :, 5:], t[:, :, 4:5].expand_as(t[:, :, 5:]))
    return total / int(mask.sum())


def _kl(logits: Any, target: Any, weight: Any = None) -> Any:
    """Summed KL divergence of Bernoullis with ``logits`` from ones with probabilities ``target``."""
    import torch.nn.functional as F

    cross = F.binary_cross_entropy_with_logits(logits, target, weight=weight, reduction="sum")
    return cross - F.binary_cross_entropy(target, target, weight=weight, reduction="sum")


# ------------------------------------------------------------------------------------------------------ data
def _input(images: np.ndarray, image_size: int) -> tuple[Any, float, tuple[int, int]]:
    """Frames as the detector feeds them (``CocoDetector.detect_batch``): scaled, grey-padded, 0..1."""
    import cv2
    import torch

    h, w = images.shape[1:3]
    scale = image_size / max(w, h)
    sw, sh = max(1, round(w * scale)), max(1, round(h * scale))
    pw, ph = -(-sw // 32) * 32, -(-sh // 32) * 32
    canvas = np.full((len(images), ph, pw, 3), 127, np.uint8)
    for i, frame in enumerate(images):
        canvas[i, :sh, :sw] = frame if (sw, sh) == (w, h) else cv2.resize(frame, (sw, sh),
                                                                         interpolation=cv2.INTER_LINEAR)
    x = torch.from_numpy(canvas).permute(0, 3, 1, 2).float().div_(255.0)
    return x.contiguous(memory_format=torch.channels_last), scale, (ph, pw)


def _targets(data: Any, idx: np.ndarray, scale: float, flips: np.ndarray, width: int) -> tuple[list[Any], list[Any]]:
    import torch

    boxes, ignores = [], []
    for k, i in enumerate(idx):
        rows = data.frame_boxes(int(i))
        xyxy = rows[:, 1:5].astype(np.float32).copy()
        if flips[k] and len(xyxy):
            xyxy[:, [0, 2]] = width - xyxy[:, [2, 0]]
        pos = ((xyxy[:, 3] - xyxy[:, 1]) >= MIN_HEIGHT) & (rows[:, 6] >= MIN_VISIBLE)
        boxes.append(torch.from_numpy(xyxy[pos] * scale))
        ignores.append(torch.from_numpy(xyxy[~pos] * scale))
    return boxes, ignores


# ------------------------------------------------------------------------------------------------------ hook
def finetune_darknet(request: Any) -> Path:
    """Fine-tune the darknet model folder ``request.weights`` (the ``coco`` system's); returns the new folder."""
    import torch

    import genesis_rl
    from genesis_rl.core.files.hashing import file_sha256
    from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json, atomic_write_text
    from genesis_rl.harden.data import concat, dataset_sha256, export_frames, original_frames
    from genesis_rl.harden.loop import finetune_config, relative_to, train_epochs
    from genesis_rl.sut.perception.coco_detector import CocoDetector

    cfg = finetune_config(DarknetFinetuneConfig, request.options, "the coco system's fine-tune")
    kwargs = dict(request.system_kwargs)
    detector = CocoDetector(request.weights, image_size=int(kwargs.get("image_size", 416)))
    net = detector.net
    base_dir = detector.folder
    original = original_frames({"map": request.map or "highway", "condition": "clear", "train_catalog_seed": 100,
                                "seed": 0, "frames_per_scene": 4}, cfg.original_frames,
                               request.work / "original_data.npz", request.progress)
    failures = concat([export_frames(f) for f in request.failures])
    if not len(failures):
        raise UserInputError(f"round {request.round}: the failure exports hold no frame to retrain on")
    data = concat([original] + [failures] * cfg.failure_repeat)

    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(np.random.SeedSequence([request.seed, request.round, 4111]))
    teacher = None
    if cfg.distill > 0:
        teacher = CocoDetector(request.weights, image_size=detector.image_size).net
        teacher.eval()
    net.train()
    for index, param in ((i, p) for i, layer in enumerate(net.layers) for p in layer.parameters()):
        param.requires_grad_(index >= cfg.freeze)
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    t0 = time.perf_counter()
    width = data.images.shape[2]

    def batch_loss(idx: np.ndarray) -> Any:
        flips = rng.random(len(idx)) < 0.5
        images = data.images[idx]
        images = np.where(flips[:, None, None, None], images[:, :, ::-1], images)
        x, scale, hw = _input(images, detector.image_size)
        boxes, ignores = _targets(data, idx, scale, flips, width)
        raw = net(x, frozen=cfg.freeze)
        loss = yolo_loss(net, raw, boxes, ignores, hw, detector.class_ids)
        if teacher is not None:
            with torch.no_grad():
                t_raw = teacher(x)
            loss = loss + cfg.distill * distillation(net, raw, t_raw, torch.from_numpy(idx < len(original)))
        return loss

    history = train_epochs(opt, params, len(data), cfg.epochs, cfg.batch_size, cfg.lr, rng, batch_loss,
                           desc=f"round {request.round}: fine-tune (darknet)" if request.progress else None)
    net.eval()
    out = request.out
    out.mkdir(parents=True, exist_ok=True)
    from genesis_rl.sut.perception.coco_detector import weights_cfg

    cfg_src = base_dir / CFG_NAME
    atomic_write_text(out / CFG_NAME, folded_cfg(weights_cfg(cfg_src.read_text(encoding="utf-8"), str(cfg_src))))
    blob = weights_bytes(net)
    atomic_write(out / WEIGHTS_NAME, lambda p: p.write_bytes(blob))
    shutil.copyfile(base_dir / "coco.names", out / "coco.names")
    atomic_write_json(out / "finetune.json", {
        "format": "genesis-rl/darknet-finetune", "genesis_rl_version": genesis_rl.__version__,
        "round": request.round, "seed": request.seed, "config": dataclasses.asdict(cfg),
        "base_weights_sha256": file_sha256(base_dir / WEIGHTS_NAME), "image_size": detector.image_size,
        "original_frames": len(original), "original_sha256": dataset_sha256(original),
        "failure_frames": len(failures), "failure_sha256": dataset_sha256(failures),
        "failure_exports": [relative_to(f, request.work) for f in request.failures],
        "history": history, "seconds": round(time.perf_counter() - t0, 1)}, indent=2)
    return out
