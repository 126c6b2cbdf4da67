"""The built-in vehicle detector (weights shipped in ``genesis_rl/sut/perception/weights/``) and a null detector.

A detector takes RGB frames (H, W, 3) uint8, as ``SensorFrame.rgb``, and returns boxes as (N, 5) float32
arrays ``x0, y0, x1, y1, score`` in the frame's pixels, best first.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.hashing import file_sha256  # noqa: F401  (read here by plug-ins before 0.30)
from genesis_rl.core.threads import INFERENCE_THREADS, pinned_threads

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
#: the shipped checkpoint (see docs/detector.md for the command that made it)
DEFAULT_WEIGHTS = WEIGHTS_DIR / "vehicle_detector.pt"
#: earlier shipped checkpoints, named by the first 12 hex digits of their sha256, so that a record written with
#: them replays with them (docs/detector.md, "Earlier weights")
ARCHIVE_DIR = WEIGHTS_DIR / "archive"
CHECKPOINT_FORMAT = "genesis-rl/vehicle-detector"
CHECKPOINT_VERSION = 1


def archived_weights(sha256: str) -> Path | None:
    """The shipped checkpoint (current or archived) whose file has this sha256, or None."""
    if not isinstance(sha256, str) or len(sha256) < 12:
        return None
    candidates = [DEFAULT_WEIGHTS, ARCHIVE_DIR / f"vehicle_detector_{sha256[:12]}.pt"]
    return next((p for p in candidates if p.is_file() and file_sha256(p) == sha256), None)


@runtime_checkable
class Detector(Protocol):
    """What the system under test needs from a detector."""

    def detect(self, rgb: np.ndarray) -> np.ndarray: ...

    def detect_batch(self, rgbs: np.ndarray) -> list[np.ndarray]: ...


def _empty() -> np.ndarray:
    return np.zeros((0, 5), np.float32)


def _check_frame(rgb: np.ndarray, what: str = "rgb") -> np.ndarray:
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"{what} must be an (H, W, 3) uint8 array, got {a.shape} {a.dtype}")
    return a


class NullDetector:
    """Sees nothing: every frame gives an empty (0, 5) array (for the perception-dependence test)."""

    score_threshold = 1.0
    weights_path: Path | None = None
    weights_sha256: str | None = None
    name = "null"

    def detect(self, rgb: np.ndarray) -> np.ndarray:
        _check_frame(rgb)
        return _empty()

    def detect_batch(self, rgbs: np.ndarray) -> list[np.ndarray]:
        return [self.detect(r) for r in rgbs]



def _first_mismatch(err: Exception) -> str:
    """One line from a load error: torch's first line only says "Error(s) in loading state_dict"; the first
    mismatched or missing tensor is on the next, so name it (and count the rest)."""
    lines = [line.strip() for line in str(err).strip().splitlines() if line.strip()]
    if len(lines) <= 1:
        return lines[0] if lines else type(err).__name__
    details = [part.strip() for line in lines[1:] for part in line.split("\t") if part.strip()]
    more = f" (and {len(details) - 1} more)" if len(details) > 1 else ""
    return f"{details[0]}{more}"


def load_checkpoint(path: Path) -> dict:
    """Read and check a detector checkpoint; any problem raises :class:`UserInputError` naming the file."""
    import torch

    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"weights '{path}' is a folder; expected a detector checkpoint file (.pt)")
    if not path.is_file():
        raise UserInputError(f"weights file {path} does not exist (expected a genesis-rl detector checkpoint, "
                             f"e.g. {DEFAULT_WEIGHTS.name} from 'genesis-rl detector train')")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001  (torch raises many types for a bad file)
        # torch's own text suggests weights_only=False, which would run code from the file: not repeated here
        raise UserInputError(f"weights file {path} is not a genesis-rl detector checkpoint (torch could not read "
                             f"it safely: {type(e).__name__}); make one with 'genesis-rl detector train'") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise UserInputError(f"weights file {path} is not a genesis-rl detector checkpoint: "
                             f"no '{CHECKPOINT_FORMAT}' format tag")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise UserInputError(f"weights file {path} has checkpoint version {ckpt.get('version')}; "
                             f"this genesis-rl reads version {CHECKPOINT_VERSION}")
    for key in ("model_config", "state_dict", "score_threshold"):
        if key not in ckpt:
            raise UserInputError(f"weights file {path} is not a genesis-rl detector checkpoint: missing '{key}'")
    return ckpt


class VehicleDetector:
    """The CenterNet-style CNN of :mod:`genesis_rl.sut.perception.model` with its trained weights.

    ``weights``: a checkpoint from ``genesis-rl detector train`` (default: the shipped one).
    ``score_threshold``: overrides the one chosen on validation data and stored in the checkpoint.
    ``num_threads``: torch CPU threads for each forward pass, pinned per call whatever the process's own
    setting (default ``core.threads.INFERENCE_THREADS``), so a pool worker and the main process compute the
    same floats.
    """

    def __init__(
        self,
        weights: str | Path | None = None,
        score_threshold: float | None = None,
        max_detections: int = 50,
        batch_size: int = 16,
        num_threads: int | None = None,
    ) -> None:
        import torch

        from genesis_rl.sut.perception.model import DetectorModelConfig, VehicleDetectorNet

        self.weights_path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
        ckpt = load_checkpoint(self.weights_path)
        try:
            self.model_config = DetectorModelConfig.from_dict(dict(ckpt["model_config"]))
            net = VehicleDetectorNet(self.model_config)
            net.load_state_dict(ckpt["state_dict"])
        except (ValueError, TypeError, RuntimeError, OverflowError) as e:
            msg = _first_mismatch(e)
            raise UserInputError(f"weights file {self.weights_path} does not match the detector network: "
                                 f"{msg}") from None
        _check_weights_finite(net, self.weights_path)
        given = ckpt["score_threshold"] if score_threshold is None else score_threshold
        where = f"weights file {self.weights_path}: score_threshold" if score_threshold is None else "score_threshold"
        thr = ranges.number(given, where, 1e-6, 1.0 - 1e-6, note="a detection score, strictly between 0 and 1")
        if max_detections < 1 or batch_size < 1:
            raise UserInputError(f"max_detections and batch_size must be >= 1, got {max_detections}, {batch_size}")
        self.score_threshold = thr
        self.max_detections = int(max_detections)
        self.batch_size = int(batch_size)
        self.metadata: dict = dict(ckpt.get("metadata", {}))
        self.num_threads = INFERENCE_THREADS if num_threads is None else int(num_threads)
        if self.num_threads < 1:
            raise UserInputError(f"num_threads = {num_threads}: must be >= 1")
        self._net = _fold_batch_norm(net.eval()).to(memory_format=torch.channels_last)
        #: uint8 -> normalised float32 per channel, one look-up instead of four passes over the frame
        self._input_table = self._net.input_table()
        self._traced: dict[tuple[int, ...], Any] = {}  # per input shape, see _forward
        self._sha256: str | None = None
        self.name = f"vehicle_detector:{self.weights_path.name}"

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) the network runs at; other frame sizes are resized to it."""
        return self.model_config.input_width, self.model_config.input_height

    @property
    def weights_sha256(self) -> str:
        """SHA-256 of the weights file (for edge-case records)."""
        if self._sha256 is None:
            self._sha256 = file_sha256(self.weights_path)
        return self._sha256

    def detect(self, rgb: np.ndarray) -> np.ndarray:
        """Boxes (N, 5) x0, y0, x1, y1, score in ``rgb``'s pixels."""
        a = _check_frame(rgb)
        return self.detect_batch(a[None])[0]

    def detect_batch(self, rgbs: np.ndarray) -> list[np.ndarray]:
        """One (N, 5) array per frame of ``rgbs`` (B, H, W, 3) uint8 (or a list of same-size frames)."""
        import cv2
        import torch

        from genesis_rl.sut.perception.model import decode

        if isinstance(rgbs, (list, tuple)):
            if not rgbs:
                return []
            rgbs = np.stack([_check_frame(r) for r in rgbs])
        a = np.asarray(rgbs)
        if a.ndim != 4 or a.shape[3] != 3 or a.dtype != np.uint8:
            raise ValueError(f"rgbs must be a (B, H, W, 3) uint8 array, got {a.shape} {a.dtype}")
        iw, ih = self.input_size
        h, w = a.shape[1:3]
        resize = (w, h) != (iw, ih)
        out: list[np.ndarray] = []
        with torch.inference_mode(), pinned_threads(self.num_threads):
            for s in range(0, len(a), self.batch_size):
                chunk = a[s : s + self.batch_size]
                if resize:
                    interp = cv2.INTER_AREA if w > iw else cv2.INTER_LINEAR
                    chunk = np.stack([cv2.resize(f, (iw, ih), interpolation=interp) for f in chunk])
                # (B, H, W, 3) float32 is (B, 3, H, W) in channels-last layout, which the net runs in
                x = torch.from_numpy(self._normalized(chunk)).permute(0, 3, 1, 2)
                dets = decode(self._forward(x), self.score_threshold, self.max_detections,
                              self.model_config.output_stride, image_size=(iw, ih))
                if resize:
                    scale = np.array([w / iw, h / ih, w / iw, h / ih, 1.0], np.float32)
                    dets = [d * scale for d in dets]
                out.extend(dets)
        return out

    def _forward(self, x: Any) -> dict[str, Any]:
        """The net on a normalised batch, through a TorchScript trace of it per input shape: the same
        kernels in the same order (bit-identical outputs, tested) without Python's module calls, about
        0.45 ms of a 4 ms frame on one thread. No numerics-changing graph rewrites (``optimize_numerics``)."""
        import torch

        from genesis_rl.sut.perception.model import NormalizedForward

        key = tuple(x.shape)
        if key not in self._traced:
            try:
                with warnings.catch_warnings():  # TorchScript is deprecated in favour of torch.compile, which
                    warnings.simplefilter("ignore")  # needs a C++ compiler and a minute's compile per process
                    traced = torch.jit.trace(NormalizedForward(self._net).eval(), x, strict=False)
                    self._traced[key] = torch.jit.freeze(traced, optimize_numerics=False)
            except Exception:  # noqa: BLE001 - a torch without TorchScript: the eager net, same numbers
                self._traced[key] = self._net.forward_normalized
        return self._traced[key](x)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_traced": {}}  # traces are remade where the detector is unpickled

    def _normalized(self, chunk: np.ndarray) -> np.ndarray:
        """(B, H, W, 3) float32: the net's normalised input, by table look-up (bit for bit its arithmetic)."""
        import cv2

        b, h, w, _ = chunk.shape
        flat = np.ascontiguousarray(chunk).reshape(b * h, w, 3)
        return cv2.LUT(flat, self._input_table).reshape(b, h, w, 3)

    def describe(self) -> dict:
        """What an edge-case record should store about this detector."""
        return {
            "name": self.name,
            "weights": str(self.weights_path),
            "weights_sha256": self.weights_sha256,
            "score_threshold": self.score_threshold,
            "input_size": list(self.input_size),
        }


def _fold_batch_norm(net: Any) -> Any:
    """The inference net with each BatchNorm folded into the conv before it (torch's
    ``fuse_conv_bn_eval``): the same function to ~1e-5 in the logits, and a third less time per frame on a
    CPU (9.2 -> 5.9 ms on one thread at 320x240), which the closed loop pays every step."""
    from torch import nn
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    for seq in net.modules():
        if not isinstance(seq, nn.Sequential):
            continue
        for i in range(len(seq) - 1):
            conv, bn = seq[i], seq[i + 1]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                seq[i] = fuse_conv_bn_eval(conv, bn)
                seq[i + 1] = nn.Identity()
    return net


#: the largest magnitude a weight may have: trained ones stay below 10 (the shipped net's largest is 8.1);
#: far larger ones overflow float32 activations into inf and NaN
MAX_WEIGHT = 1e6


def _check_weights_finite(net: Any, path: Path) -> None:
    """Refuse weights that are NaN, infinite or absurdly large: a net with them detects nothing (IoU 0
    everywhere) and every result would silently measure a broken detector."""
    import torch

    with torch.no_grad():
        for name, tensor in net.state_dict().items():
            if not tensor.is_floating_point() or tensor.numel() == 0:
                continue
            finite = torch.isfinite(tensor)
            if not bool(finite.all()):
                bad = int((~finite).sum())
                raise UserInputError(f"weights file {path}: tensor '{name}' has {bad} of {tensor.numel()} values "
                                     "that are NaN or infinite; the file is damaged: retrain it ('genesis-rl "
                                     "detector train') or use the shipped weights")
            if name.endswith("running_var") and bool((tensor < 0).any()):
                raise UserInputError(f"weights file {path}: tensor '{name}' (a variance) has negative values; "
                                     "the file is damaged: retrain it ('genesis-rl detector train') or use the "
                                     "shipped weights")
            largest = float(tensor.abs().max())
            if largest > MAX_WEIGHT:
                raise UserInputError(f"weights file {path}: tensor '{name}' holds a value of magnitude "
                                     f"{largest:.3g}, beyond {MAX_WEIGHT:g}; the file is damaged: retrain it "
                                     "('genesis-rl detector train') or use the shipped weights")


def read_weights_json(weights: Path) -> dict:
    """The metrics JSON written next to a checkpoint (empty dict when there is none)."""
    p = Path(weights).with_suffix(".json")
    if not p.is_file():
        return {}
    try:
        from genesis_rl.core.parsing import loads_json

        return loads_json(p.read_text(encoding="utf-8"), f"weights metadata '{p}'")
    except UserInputError:
        raise
    except (OSError, ValueError) as e:
        raise UserInputError(f"weights metadata {p} is not valid JSON: {e}") from None
