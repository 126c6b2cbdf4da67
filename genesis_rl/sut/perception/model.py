"""The built-in vehicle detector network: a small CenterNet (objects as points) in plain torch.

The network maps an RGB frame to three maps at output stride 4: a heatmap of vehicle box centres (one
class), the box size (log width and log height in input pixels) and the sub-pixel offset of the centre
inside its output cell. :func:`encode_targets` turns ground-truth boxes into those maps (a gaussian bump
per box, CenterNet's radius rule) and :func:`decode` turns network outputs back into boxes: local maxima
of the heatmap (3x3 max-pool peak pick) above a score threshold.

Boxes are ``x0, y0, x1, y1`` in input-image pixels (x1, y1 exclusive, as the renderer's ground truth).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from genesis_rl.core import ranges

#: heatmap bias at init: sigmoid(-2.19) = 0.1 (CenterNet / focal-loss prior)
HEATMAP_BIAS_INIT = -2.19


@dataclass(frozen=True)
class DetectorModelConfig:
    """Architecture and input geometry; stored in the checkpoint so weights load into the right net."""

    channels: tuple[int, ...] = (16, 24, 32, 48, 64)  # widths at strides 2, 4, 8, 16, 32
    fpn_channels: int = 32  # width of the merged stride-4 feature map and the heads
    input_width: int = 320  # [px] frames of another size are resized to this
    input_height: int = 240  # [px]
    output_stride: int = 4

    def __post_init__(self) -> None:
        # sizes within reason: a checkpoint that says 10^9 channels must not allocate terabytes
        for i, c in enumerate(self.channels):
            ranges.number(c, f"model_config.channels[{i}]", 4, 1024, "channels", integer=True)
        ranges.number(self.fpn_channels, "model_config.fpn_channels", 4, 1024, "channels", integer=True)
        ranges.number(self.input_width, "model_config.input_width", 32, 4096, "px", integer=True)
        ranges.number(self.input_height, "model_config.input_height", 16, 4096, "px", integer=True)
        if len(self.channels) != 5 or any(int(c) < 4 for c in self.channels):
            raise ValueError(f"channels must be 5 widths >= 4 (strides 2..32), got {self.channels}")
        if self.output_stride != 4:
            raise ValueError(f"output_stride must be 4, got {self.output_stride}")
        if self.input_width % 32 or self.input_height % 16:
            raise ValueError(
                f"input size must be a multiple of 32 x 16, got {self.input_width}x{self.input_height}"
            )

    def as_dict(self) -> dict:
        d = asdict(self)
        d["channels"] = list(self.channels)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> DetectorModelConfig:
        known = {"channels", "fpn_channels", "input_width", "input_height", "output_stride"}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown model config keys {sorted(unknown)}; allowed: {sorted(known)}")
        d = dict(d)
        if "channels" in d:
            d["channels"] = tuple(int(c) for c in d["channels"])
        return cls(**d)

    @property
    def output_size(self) -> tuple[int, int]:
        """(height, width) of the output maps."""
        return self.input_height // self.output_stride, self.input_width // self.output_stride


def _cbr(cin: int, cout: int, stride: int = 1, k: int = 3) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)
    )


class VehicleDetectorNet(nn.Module):
    """Five stride-2 stages (conv-BN-ReLU), a top-down merge to stride 4, three 1x1 heads.

    ``forward`` takes float images (B, 3, H, W) in 0..1 and returns ``{"heatmap": logits (B,1,h,w),
    "size": log(w, h) in pixels (B,2,h,w), "offset": sub-cell offset (B,2,h,w)}``.
    """

    mean: torch.Tensor  # buffers (register_buffer), typed here for the checker
    std: torch.Tensor

    def __init__(self, config: DetectorModelConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or DetectorModelConfig()
        c = cfg.channels
        self.register_buffer("mean", torch.tensor([0.45, 0.45, 0.45]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.25, 0.25, 0.25]).view(1, 3, 1, 1), persistent=False)
        self.stem = _cbr(3, c[0], 2)  # /2
        self.s4 = nn.Sequential(_cbr(c[0], c[1], 2), _cbr(c[1], c[1]))  # /4
        self.s8 = nn.Sequential(_cbr(c[1], c[2], 2), _cbr(c[2], c[2]))  # /8
        self.s16 = nn.Sequential(_cbr(c[2], c[3], 2), _cbr(c[3], c[3]))  # /16
        self.s32 = nn.Sequential(_cbr(c[3], c[4], 2), _cbr(c[4], c[4]))  # /32
        f = cfg.fpn_channels
        self.lat4 = nn.Conv2d(c[1], f, 1)
        self.lat8 = nn.Conv2d(c[2], f, 1)
        self.lat16 = nn.Conv2d(c[3], f, 1)
        self.lat32 = nn.Conv2d(c[4], f, 1)
        self.merge = _cbr(f, f)
        self.head = _cbr(f, f)
        self.heatmap = nn.Conv2d(f, 1, 1)
        self.size = nn.Conv2d(f, 2, 1)
        self.offset = nn.Conv2d(f, 2, 1)
        heatmap_bias, size_bias, offset_bias = self.heatmap.bias, self.size.bias, self.offset.bias
        assert heatmap_bias is not None and size_bias is not None and offset_bias is not None  # bias=True
        nn.init.constant_(heatmap_bias, HEATMAP_BIAS_INIT)
        nn.init.normal_(self.heatmap.weight, std=0.01)
        nn.init.normal_(self.size.weight, std=0.01)
        nn.init.constant_(size_bias, math.log(16.0))
        nn.init.normal_(self.offset.weight, std=0.01)
        nn.init.constant_(offset_bias, 0.5)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.forward_normalized((x - self.mean) / self.std)

    def input_table(self) -> np.ndarray:
        """(1, 256, 3) float32: what ``forward`` feeds its first layer for each 8-bit value of each channel,
        computed with the same float32 operations (``/ 255``, ``- mean``, ``/ std``), so that a table look-up
        of a uint8 frame followed by :meth:`forward_normalized` is bit for bit ``forward(frame / 255)``."""
        v = torch.arange(256, dtype=torch.float32).view(1, 1, 256, 1).expand(1, 3, 256, 1).contiguous()
        with torch.no_grad():
            t = (v.div_(255.0) - self.mean) / self.std  # (1, 3, 256, 1)
        return np.ascontiguousarray(t[0, :, :, 0].T.numpy()).reshape(1, 256, 3)

    def forward_normalized(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """``forward`` of an image already normalised by ``mean`` and ``std``."""
        x4 = self.s4(self.stem(x))
        x8 = self.s8(x4)
        x16 = self.s16(x8)
        x32 = self.s32(x16)
        p = self.lat32(x32)
        p = self.lat16(x16) + F.interpolate(p, size=x16.shape[-2:], mode="nearest")
        p = self.lat8(x8) + F.interpolate(p, size=x8.shape[-2:], mode="nearest")
        p = self.lat4(x4) + F.interpolate(p, size=x4.shape[-2:], mode="nearest")
        h = self.head(self.merge(p))
        return {"heatmap": self.heatmap(h), "size": self.size(h), "offset": self.offset(h)}


class NormalizedForward(nn.Module):
    """A net's ``forward_normalized`` as a module's ``forward``: what the detector traces with TorchScript."""

    def __init__(self, net: VehicleDetectorNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.net.forward_normalized(x)


# ---------------------------------------------------------------------------------------------- targets
def gaussian_radius(height: float, width: float, min_overlap: float = 0.7) -> float:
    """CenterNet's radius: the largest centre shift that keeps IoU >= ``min_overlap`` (in output cells)."""
    a1, b1 = 1.0, height + width
    c1 = width * height * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1**2 - 4 * a1 * c1)) / 2
    a2, b2 = 4.0, 2 * (height + width)
    c2 = (1 - min_overlap) * width * height
    r2 = (b2 + math.sqrt(b2**2 - 4 * a2 * c2)) / 2
    a3, b3 = 4 * min_overlap, -2 * min_overlap * (height + width)
    c3 = (min_overlap - 1) * width * height
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def encode_targets(
    boxes: np.ndarray,
    out_h: int,
    out_w: int,
    stride: int = 4,
    ignore: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Targets of one image for ``boxes`` (N, 4+) x0, y0, x1, y1 in input pixels.

    Returns ``heatmap`` (1, h, w) with a gaussian peak of 1 at each centre cell, ``size`` and ``offset``
    (2, h, w) set at the centre cells, ``reg_mask`` (h, w) 1 at centre cells, and ``hm_weight`` (1, h, w):
    0 inside the boxes of ``ignore`` (N, 4+) vehicles, which the heatmap loss must not punish, else 1.
    """
    heat = np.zeros((out_h, out_w), np.float32)
    size = np.zeros((2, out_h, out_w), np.float32)
    offset = np.zeros((2, out_h, out_w), np.float32)
    reg_mask = np.zeros((out_h, out_w), np.float32)
    weight = np.ones((out_h, out_w), np.float32)
    if ignore is not None:
        for b in np.asarray(ignore, np.float64).reshape(-1, max(4, np.shape(ignore)[-1] if len(ignore) else 4)):
            x0, y0 = int(math.floor(b[0] / stride)), int(math.floor(b[1] / stride))
            x1, y1 = int(math.ceil(b[2] / stride)), int(math.ceil(b[3] / stride))
            weight[max(0, y0) : max(0, y1), max(0, x0) : max(0, x1)] = 0.0
    boxes = np.asarray(boxes, np.float64)
    if boxes.size:
        boxes = boxes.reshape(len(boxes), -1)
        # large boxes first so that a small one's centre wins a shared cell
        order = np.argsort(-(boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]), kind="stable")
        for b in boxes[order]:
            w, h = float(b[2] - b[0]), float(b[3] - b[1])
            if w <= 0 or h <= 0:
                continue
            cx, cy = (b[0] + b[2]) / 2 / stride, (b[1] + b[3]) / 2 / stride
            ix, iy = min(out_w - 1, max(0, int(cx))), min(out_h - 1, max(0, int(cy)))
            r = max(0, int(gaussian_radius(h / stride, w / stride)))
            sigma = (2 * r + 1) / 6.0
            ys = np.arange(max(0, iy - r), min(out_h, iy + r + 1))
            xs = np.arange(max(0, ix - r), min(out_w, ix + r + 1))
            g = np.exp(-((ys[:, None] - iy) ** 2 + (xs[None, :] - ix) ** 2) / (2 * sigma * sigma)).astype(np.float32)
            sub = heat[ys[0] : ys[-1] + 1, xs[0] : xs[-1] + 1]
            np.maximum(sub, g, out=sub)
            heat[iy, ix] = 1.0
            weight[iy, ix] = 1.0
            size[:, iy, ix] = (math.log(w), math.log(h))
            offset[:, iy, ix] = (cx - ix, cy - iy)
            reg_mask[iy, ix] = 1.0
    return {
        "heatmap": heat[None],
        "size": size,
        "offset": offset,
        "reg_mask": reg_mask,
        "hm_weight": weight[None],
    }


# ---------------------------------------------------------------------------------------------- decode
def decode(
    outputs: dict[str, torch.Tensor],
    score_threshold: float = 0.3,
    max_detections: int = 50,
    stride: int = 4,
    image_size: tuple[int, int] | None = None,
    heatmap_is_logits: bool = True,
    nms_iou: float | None = 0.6,
) -> list[np.ndarray]:
    """Boxes from network outputs: one (N, 5) float32 array x0, y0, x1, y1, score per image, best first.

    Peaks are cells equal to the 3x3 max of their neighbourhood with a score >= ``score_threshold``;
    ``image_size`` (width, height) clips the boxes to the image. A small greedy box NMS (``nms_iou``; None
    turns it off) drops the second peak a long vehicle (bus, truck) sometimes gets.
    """
    heat = outputs["heatmap"].detach().float()
    if heatmap_is_logits:
        heat = torch.sigmoid(heat)
    b, _, h, w = heat.shape
    peaks = heat * (F.max_pool2d(heat, 3, stride=1, padding=1) == heat)
    k = min(int(max_detections), h * w)
    scores, idx = torch.topk(peaks.view(b, -1), k)
    size = outputs["size"].detach().float().view(b, 2, -1)
    off = outputs["offset"].detach().float().view(b, 2, -1)
    result: list[np.ndarray] = []
    for i in range(b):
        keep = scores[i] >= score_threshold
        sc, ix = scores[i][keep], idx[i][keep]
        if ix.numel() == 0:
            result.append(np.zeros((0, 5), np.float32))
            continue
        ys, xs = (ix // w).float(), (ix % w).float()
        cx = (xs + off[i, 0, ix]) * stride
        cy = (ys + off[i, 1, ix]) * stride
        bw, bh = torch.exp(size[i, 0, ix].clamp(max=8.0)), torch.exp(size[i, 1, ix].clamp(max=8.0))
        boxes = torch.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2, sc], dim=1)
        if image_size is not None:
            boxes[:, 0:4:2] = boxes[:, 0:4:2].clamp(0, image_size[0])
            boxes[:, 1:4:2] = boxes[:, 1:4:2].clamp(0, image_size[1])
        out = boxes.numpy().astype(np.float32)
        result.append(nms(out, nms_iou) if nms_iou is not None and len(out) > 1 else out)
    return result


def nms(dets: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy NMS of (N, 5) detections sorted best first: drop any box overlapping a kept one by IoU > threshold."""
    iou = box_iou(dets, dets)
    keep = np.ones(len(dets), bool)
    for i in range(len(dets)):
        if keep[i]:
            keep[i + 1 :] &= iou[i, i + 1 :] <= iou_threshold
    return dets[keep]


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix (len(a), len(b)) of xyxy boxes (extra columns, e.g. scores, ignored)."""
    from genesis_rl.sim.geometry import iou_matrix

    a = np.asarray(a, np.float64).reshape(-1, max(4, np.shape(a)[-1] if np.size(a) else 4))[:, :4]
    b = np.asarray(b, np.float64).reshape(-1, max(4, np.shape(b)[-1] if np.size(b) else 4))[:, :4]
    return iou_matrix(a, b)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def stack_targets(targets: Sequence[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.stack([t[k] for t in targets])) for k in targets[0]}
