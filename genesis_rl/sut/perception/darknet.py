"""A darknet YOLO (v3 / v3-tiny) network in plain torch, built from its ``.cfg`` and filled from its
``.weights`` file.

Why not OpenCV: ``cv2.dnn.readNetFromDarknet`` left OpenCV in release 5, and pinning an old OpenCV for one
reader would hold back every other use. Why not a pickle: a darknet ``.weights`` file is a flat array of
float32 numbers after a short header, so reading it runs no code from the file (unlike a ``.pt`` file).

Supported layer types: ``convolutional`` (with or without batch norm; ``leaky`` or ``linear``), ``maxpool``
(darknet's "same" pooling for stride 1), ``upsample``, ``route`` and ``yolo``: everything yolov3-tiny and
yolov3 use (``shortcut`` too). Batch norm is folded into the convolution on load, which is exact and saves
a pass per layer.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from genesis_rl.core.errors import UserInputError

Section = dict[str, str]


def parse_cfg(text: str, source: str = "cfg") -> list[tuple[str, Section]]:
    """``[type]`` sections with their ``key=value`` options, in file order (comments and blanks dropped)."""
    sections: list[tuple[str, Section]] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        head = re.fullmatch(r"\[(\w+)\]", line)
        if head:
            sections.append((head.group(1), {}))
        elif "=" in line and sections:
            key, value = line.split("=", 1)
            sections[-1][1][key.strip()] = value.strip()
        else:
            raise UserInputError(f"{source} line {number}: '{raw.strip()}' is neither a [section] nor key=value")
    if not sections or sections[0][0] not in ("net", "network"):
        raise UserInputError(f"{source}: a darknet cfg starts with a [net] section")
    return sections


def _int(section: Section, key: str, default: int | None = None, source: str = "cfg") -> int:
    if key not in section:
        if default is None:
            raise UserInputError(f"{source}: a layer lacks '{key}'")
        return default
    try:
        return int(section[key])
    except ValueError:
        raise UserInputError(f"{source}: '{key}' = '{section[key]}' is not an integer") from None


@dataclass(frozen=True)
class YoloHead:
    """One detection scale: its anchors (pixels of the network input) and class count."""

    anchors: tuple[tuple[float, float], ...]
    classes: int


class _SamePool(nn.Module):
    """darknet's maxpool: with stride 1 it pads right/bottom by replicating, so the size is kept."""

    def __init__(self, size: int, stride: int) -> None:
        super().__init__()
        self.size, self.stride = size, stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.stride == 1:
            x = F.pad(x, (0, self.size - 1, 0, self.size - 1), mode="replicate")
        return F.max_pool2d(x, self.size, self.stride)


class DarknetYolo(nn.Module):
    """The network of a darknet YOLO cfg. ``forward`` returns one raw map per YOLO head, (B, A*(5+C), H, W)."""

    def __init__(self, cfg_text: str, source: str = "cfg") -> None:
        super().__init__()
        sections = parse_cfg(cfg_text, source)
        net = sections[0][1]
        self.input_size = (_int(net, "width", 416, source), _int(net, "height", 416, source))
        self.layers = nn.ModuleList()
        self.kinds: list[str] = []
        self.routes: dict[int, list[int]] = {}
        self.heads: dict[int, YoloHead] = {}
        self.bn_convs: list[int] = []  # conv layers whose weights file entry carries batch-norm numbers
        channels = [_int(net, "channels", 3, source)]
        out_channels: list[int] = []
        for index, (kind, sec) in enumerate(sections[1:]):
            c_in = out_channels[-1] if out_channels else channels[0]
            module: nn.Module
            if kind == "convolutional":
                filters, size = _int(sec, "filters", source=source), _int(sec, "size", source=source)
                stride, pad = _int(sec, "stride", 1, source), _int(sec, "pad", 0, source)
                bn = _int(sec, "batch_normalize", 0, source) == 1
                activation = sec.get("activation", "linear")
                if activation not in ("leaky", "linear"):
                    raise UserInputError(f"{source}: activation '{activation}' is not supported "
                                         f"(allowed: leaky, linear)")
                conv = nn.Conv2d(c_in, filters, size, stride, (size - 1) // 2 if pad else 0, bias=True)
                module = nn.Sequential(conv, nn.LeakyReLU(0.1) if activation == "leaky" else nn.Identity())
                if bn:
                    self.bn_convs.append(index)
                c_out = filters
            elif kind == "maxpool":
                module = _SamePool(_int(sec, "size", source=source), _int(sec, "stride", source=source))
                c_out = c_in
            elif kind == "upsample":
                module = nn.Upsample(scale_factor=_int(sec, "stride", 2, source), mode="nearest")
                c_out = c_in
            elif kind == "route":
                refs = [int(v) for v in sec["layers"].split(",")]
                refs = [r if r >= 0 else index + r for r in refs]
                if any(not 0 <= r < index for r in refs):
                    raise UserInputError(f"{source}: route layer {index} refers outside 0..{index - 1}: {refs}")
                self.routes[index] = refs
                module = nn.Identity()
                c_out = sum(out_channels[r] for r in refs)
            elif kind == "shortcut":
                ref = int(sec["from"])
                self.routes[index] = [index + ref if ref < 0 else ref]
                module = nn.Identity()
                c_out = c_in
            elif kind == "yolo":
                mask = [int(v) for v in sec["mask"].split(",")]
                values = [float(v) for v in sec["anchors"].split(",")]
                pairs = list(zip(values[0::2], values[1::2], strict=True))
                self.heads[index] = YoloHead(tuple(pairs[m] for m in mask), _int(sec, "classes", source=source))
                module = nn.Identity()
                c_out = c_in
            else:
                raise UserInputError(f"{source}: layer type [{kind}] is not supported (allowed: convolutional, "
                                     f"maxpool, upsample, route, shortcut, yolo)")
            self.layers.append(module)
            self.kinds.append(kind)
            out_channels.append(c_out)
        if not self.heads:
            raise UserInputError(f"{source}: no [yolo] layer")
        classes = {h.classes for h in self.heads.values()}
        if len(classes) != 1:
            raise UserInputError(f"{source}: [yolo] layers disagree on classes: {sorted(classes)}")
        self.classes = classes.pop()

    def forward(self, x: torch.Tensor, frozen: int = 0) -> list[torch.Tensor]:
        """The raw head maps; the first ``frozen`` layers run without gradients (a fine-tune's fixed features)."""
        outputs: list[torch.Tensor] = []
        raw: list[torch.Tensor] = []
        grad = torch.is_grad_enabled()
        for index, (kind, layer) in enumerate(zip(self.kinds, self.layers, strict=True)):
            with torch.set_grad_enabled(grad and index >= frozen):
                if kind == "route":
                    refs = self.routes[index]
                    x = outputs[refs[0]] if len(refs) == 1 else torch.cat([outputs[r] for r in refs], 1)
                elif kind == "shortcut":
                    x = x + outputs[self.routes[index][0]]
                elif kind == "yolo":
                    raw.append(x)
                else:
                    x = layer(x)
            outputs.append(x)
        return raw

    def load_weights(self, data: bytes, source: str = "weights") -> None:
        """Fill the convolutions from a darknet ``.weights`` file's bytes, folding batch norm in.

        Layout: int32 major, minor, revision; a 'seen' counter (int64 from version 0.2, int32 before); then
        per conv layer in order: [beta, gamma, mean, var] (with batch norm) or bias, then the kernel. The
        file must hold exactly that many numbers: a truncated or padded file is refused.
        """
        if len(data) < 20:
            raise UserInputError(f"{source}: {len(data)} bytes is too short for a darknet weights file")
        major, minor, _ = np.frombuffer(data, "<i4", 3)
        offset = 20 if major * 10 + minor >= 2 else 16
        if (len(data) - offset) % 4:
            raise UserInputError(f"{source}: the payload is not a whole number of float32 values")
        values = np.frombuffer(data, "<f4", offset=offset)
        expected = 0
        for index, kind in enumerate(self.kinds):
            if kind == "convolutional":
                conv = self._conv(index)
                n = conv.out_channels
                expected += (4 * n if index in self.bn_convs else n) + conv.weight.numel()
        if values.size != expected:
            raise UserInputError(f"{source}: holds {values.size} numbers, the cfg needs {expected} "
                                 f"(a different model, or a damaged file)")
        if not np.isfinite(values).all():
            raise UserInputError(f"{source}: holds non-finite numbers")
        pos = 0

        def take(count: int) -> torch.Tensor:
            nonlocal pos
            chunk = torch.from_numpy(values[pos:pos + count].copy())
            pos += count
            return chunk

        with torch.no_grad():
            for index, kind in enumerate(self.kinds):
                if kind != "convolutional":
                    continue
                conv = self._conv(index)
                n = conv.out_channels
                if index in self.bn_convs:
                    beta, gamma, mean, var = take(n), take(n), take(n), take(n)
                    weight = take(conv.weight.numel()).view_as(conv.weight)
                    scale = gamma / torch.sqrt(var + 1e-5)  # darknet's epsilon (.000001 in some forks)
                    conv.weight.copy_(weight * scale.view(-1, 1, 1, 1))
                    assert conv.bias is not None
                    conv.bias.copy_(beta - mean * scale)
                else:
                    assert conv.bias is not None
                    conv.bias.copy_(take(n))
                    conv.weight.copy_(take(conv.weight.numel()).view_as(conv.weight))

    def _conv(self, index: int) -> nn.Conv2d:
        seq = self.layers[index]
        assert isinstance(seq, nn.Sequential)
        conv = seq[0]
        assert isinstance(conv, nn.Conv2d)
        return conv

    def decode(self, raw: list[torch.Tensor], input_hw: tuple[int, int]) -> torch.Tensor:
        """(B, N, 5 + C): box centre x, y, width, height in input pixels, objectness, per-class probability."""
        h_in, w_in = input_hw
        decoded = []
        for out, head in zip(raw, self.heads.values(), strict=True):
            b, _, gh, gw = out.shape
            a = len(head.anchors)
            p = out.view(b, a, 5 + head.classes, gh, gw).permute(0, 1, 3, 4, 2)
            gy, gx = torch.meshgrid(torch.arange(gh), torch.arange(gw), indexing="ij")
            anchors = torch.tensor(head.anchors, dtype=out.dtype).view(1, a, 1, 1, 2)
            xy = (torch.sigmoid(p[..., :2]) + torch.stack([gx, gy], -1)) * torch.tensor([w_in / gw, h_in / gh])
            wh = torch.exp(p[..., 2:4].clamp(max=10.0)) * anchors
            rest = torch.sigmoid(p[..., 4:])
            decoded.append(torch.cat([xy, wh, rest], -1).reshape(b, -1, 5 + head.classes))
        return torch.cat(decoded, 1)


def load_darknet(cfg_path: Path, weights_path: Path) -> DarknetYolo:
    """Build the network of ``cfg_path`` and fill it from ``weights_path`` (eval mode)."""
    model = DarknetYolo(cfg_path.read_text(encoding="utf-8"), source=str(cfg_path))
    model.load_weights(weights_path.read_bytes(), source=str(weights_path))
    return model.eval()


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression, best score first (boxes x0, y0, x1, y1)."""
    order = np.argsort(-scores, kind="stable")
    keep: list[int] = []
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    while order.size:
        i = int(order[0])
        keep.append(i)
        rest = order[1:]
        xx0 = np.maximum(boxes[i, 0], boxes[rest, 0])
        yy0 = np.maximum(boxes[i, 1], boxes[rest, 1])
        xx1 = np.minimum(boxes[i, 2], boxes[rest, 2])
        yy1 = np.minimum(boxes[i, 3], boxes[rest, 3])
        inter = np.clip(xx1 - xx0, 0, None) * np.clip(yy1 - yy0, 0, None)
        iou = inter / np.maximum(area[i] + area[rest] - inter, 1e-9)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)
