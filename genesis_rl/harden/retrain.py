"""The retrain hook of a hardening round: what it is given (:class:`RetrainRequest`), the built-in one
(:func:`finetune_detector`: fine-tunes a genesis-rl detector checkpoint on the failure frames mixed with its own
training data) and how a user's hook is named (``package.module:function``, gated like every plug-in).

A hook is a function ``hook(request: RetrainRequest) -> Path`` that writes new weights under ``request.out`` and
returns their path (a file or a folder): the round then runs the system with ``system_kwargs["weights"]`` set to
it, so a user's system reads its weights from a ``weights`` argument, as the built-in ones do.
"""

from __future__ import annotations

import dataclasses
import io
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.harden.loop import finetune_config, relative_to, train_epochs

#: the systems whose weights are genesis-rl detector checkpoints (the built-in fine-tune retrains them)
CHECKPOINT_SYSTEMS = ("builtin", "latency", "adaptive")
BUILTIN_HOOK = "builtin"


@dataclass(frozen=True)
class FinetuneConfig:
    """The built-in fine-tune: a few epochs from the current weights at a low learning rate, on every round's
    failure frames so far (each seen ``failure_repeat`` times an epoch) mixed with ``original_frames`` frames of
    the detector's own training data (so that it does not forget clear weather)."""

    epochs: int = 4
    lr: float = 5e-4  # Adam, cosine decay to 2 %; the original training peaked at 2e-3
    original_frames: int = 800
    failure_repeat: int = 2
    batch_size: int = 32
    threads: int = 2
    #: re-pick the score threshold as ``detector train`` picks it (best F1 on the detector's own validation
    #: frames, ``validation_frames`` of them); False keeps the checkpoint's
    repick_threshold: bool = True
    validation_frames: int = 480
    #: weight of the distillation term: on the original frames, the KL divergence of the new heatmap from the
    #: starting weights' (learning without forgetting, Li & Hoiem 2016); 0 turns it off
    distill: float = 5.0

    def __post_init__(self) -> None:
        if not isinstance(self.repick_threshold, bool):
            raise UserInputError(f"harden finetune.repick_threshold = {self.repick_threshold!r}; allowed: true, false")
        for name in ("epochs", "original_frames", "failure_repeat", "batch_size", "threads", "validation_frames"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise UserInputError(f"harden finetune.{name} = {value!r}; allowed: an integer >= 1")
        if not (isinstance(self.distill, (int, float)) and 0 <= self.distill <= 100):
            raise UserInputError(f"harden finetune.distill = {self.distill!r}; allowed: a number in [0, 100]")
        if not (isinstance(self.lr, (int, float)) and 0 < self.lr <= 0.1):
            raise UserInputError(f"harden finetune.lr = {self.lr!r}; allowed: a number in (0, 0.1]")


@dataclass(frozen=True)
class RetrainRequest:
    """What a retrain hook is given. ``failures``: the export folders (YOLO layout, ``metadata.jsonl`` with every
    frame's boxes, distance, visibility, weather, policy, scene and step; docs/evaluation.md) of this round's
    and every earlier round's in-ODD failure frames, before the impact, and near misses' frames, before the
    closest approach; ``weights``: the weights this round
    starts from; ``out``: an empty folder for the new weights; ``seed``: every draw of the retraining."""

    round: int
    system: str
    weights: Path
    failures: tuple[Path, ...]
    out: Path
    seed: int
    #: the harden folder: the built-in hook keeps its rendered original data there, shared by the rounds
    work: Path
    options: dict[str, Any] = field(default_factory=dict)
    progress: bool = False
    map: str = ""  # the campaign's map (the coco fine-tune renders its clear-day frames there)
    system_kwargs: dict[str, Any] = field(default_factory=dict)  # the campaign's system arguments


Hook = Callable[[RetrainRequest], Path]


def load_hook(name: str) -> Hook:
    """The hook ``name`` names: ``builtin`` or ``package.module:function`` (its module must be one the command
    line names, as every plug-in's)."""
    if name == BUILTIN_HOOK:
        return builtin_hook
    from genesis_rl.core.plugins import load_function

    module_name, sep, func_name = name.partition(":")
    if not sep or not module_name or not func_name:
        raise UserInputError(f"--retrain '{name}' is neither '{BUILTIN_HOOK}' nor an import path "
                             "'package.module:function'")
    return load_function(name, "retrain hook")


def builtin_hook(request: RetrainRequest) -> Path:
    """``--retrain builtin``: the fine-tune of the system's kind (a genesis-rl checkpoint, or coco's darknet)."""
    if request.system == "coco":
        from genesis_rl.harden.retrain_darknet import finetune_darknet

        return finetune_darknet(request)
    return finetune_detector(request)


def check_options(options: dict[str, Any], system: str | None = None) -> None:
    """Refuse built-in fine-tune settings that the fine-tune of ``system`` (None: either) does not know, or bad
    values (before anything runs)."""
    from genesis_rl.harden.retrain_darknet import DarknetFinetuneConfig

    if system is not None:
        finetune_config(DarknetFinetuneConfig if system == "coco" else FinetuneConfig, options, f"system '{system}'")
        return
    configs: tuple[type, ...] = (FinetuneConfig, DarknetFinetuneConfig)
    fields = [{f.name for f in dataclasses.fields(c)} for c in configs]
    unknown = sorted(set(options) - set().union(*fields))
    if unknown:
        raise UserInputError(f"harden finetune: unknown setting(s) {unknown}; allowed: "
                             f"{', '.join(sorted(set().union(*fields)))}")
    for config, names in zip(configs, fields, strict=True):
        finetune_config(config, {k: v for k, v in options.items() if k in names}, config.__name__)


def base_train_config(weights: Path) -> dict[str, Any]:
    """The recipe a checkpoint records (``metadata.train_config``); the defaults for one that records none."""
    from genesis_rl.sut.perception.detector import load_checkpoint
    from genesis_rl.sut.perception.train import DetectorTrainConfig

    recorded = dict(load_checkpoint(weights).get("metadata", {}).get("train_config") or {})
    known = {f.name for f in dataclasses.fields(DetectorTrainConfig)}
    return {**DetectorTrainConfig().as_dict(), **{k: v for k, v in recorded.items() if k in known}}


def _repick_threshold(net: Any, ckpt: dict[str, Any], recipe: dict[str, Any], train_cfg: Any, cfg: FinetuneConfig,
                      request: RetrainRequest) -> tuple[float, dict[str, Any]]:
    """The threshold with the best F1 on the detector's own validation frames (as ``detector train`` picks it):
    fine-tuning on failure frames shifts the scores, so the threshold picked for the old weights no longer sits
    at the same operating point. Both thresholds' validation figures are returned for the record."""
    from genesis_rl.harden.data import original_frames
    from genesis_rl.sut.perception.train import THRESHOLD_GRID, pick_threshold, predict_boxes, round_for_json

    val = original_frames(recipe, cfg.validation_frames, request.work / "validation_data.npz", request.progress,
                          split="val")
    best, by_t = pick_threshold(predict_boxes(net, val, train_cfg, THRESHOLD_GRID[0]), val)
    old = float(ckpt["score_threshold"])
    nearest_old = min(THRESHOLD_GRID, key=lambda t: abs(t - old))
    best, nearest_old = float(best), float(nearest_old)  # numpy scalars would not load with weights_only
    record = {"frames": len(val), "threshold": best, "precision": round_for_json(by_t[best].precision),
              "recall": round_for_json(by_t[best].recall), "at_old_threshold": {
                  "threshold": nearest_old, "precision": round_for_json(by_t[nearest_old].precision),
                  "recall": round_for_json(by_t[nearest_old].recall)}}
    return float(best), record


def _distillation(out: dict[str, Any], teacher: Any, x: Any, original: np.ndarray) -> Any:
    """Per original frame, the summed KL divergence of the heatmap's per-pixel Bernoulli from the starting
    weights' on the same (augmented) input: keeps what the detector fired on, and did not, where it was right."""
    import torch
    import torch.nn.functional as F

    mask = torch.from_numpy(original)
    if not bool(mask.any()):
        return torch.zeros(())
    with torch.no_grad():
        target = torch.sigmoid(teacher(x[mask])["heatmap"].float())
    logits = out["heatmap"][mask].float()
    cross = F.binary_cross_entropy_with_logits(logits, target, reduction="sum")
    entropy = F.binary_cross_entropy(target, target, reduction="sum")
    return (cross - entropy) / int(mask.sum())


def _train_frozen_norms(net: Any) -> None:
    """Training mode with every batch norm kept in eval mode: a few hundred frames of one condition would pull
    the running statistics that every clear-day frame is normalised by (the seesaw's first cause)."""
    import torch

    net.train()
    for module in net.modules():
        if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
            module.eval()


def finetune_detector(request: RetrainRequest) -> Path:
    """The built-in hook: fine-tune the genesis-rl detector checkpoint ``request.weights``; returns the new
    checkpoint (its score threshold kept: the clear-day check judges the same operating point)."""
    import torch

    import genesis_rl
    from genesis_rl.core.files.hashing import file_sha256
    from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json
    from genesis_rl.harden.data import concat, dataset_sha256, export_frames, original_frames
    from genesis_rl.sut.perception.detector import load_checkpoint
    from genesis_rl.sut.perception.model import DetectorModelConfig, VehicleDetectorNet
    from genesis_rl.sut.perception.train import (
        METRICS_NAME,
        WEIGHTS_NAME,
        DetectorTrainConfig,
        detector_loss,
        training_batch,
    )

    if request.system not in CHECKPOINT_SYSTEMS:
        raise UserInputError(f"--retrain builtin fine-tunes genesis-rl detector checkpoints (systems "
                             f"{', '.join(CHECKPOINT_SYSTEMS)}) and coco's darknet model, not system "
                             f"'{request.system}'; pass --retrain package.module:function, a hook that retrains its "
                             "weights (docs/harden.md)")
    cfg = finetune_config(FinetuneConfig, request.options, "a genesis-rl detector's fine-tune")
    ckpt = load_checkpoint(request.weights)
    recipe = base_train_config(request.weights)
    train_cfg = DetectorTrainConfig(**{**recipe, "channels": tuple(recipe["channels"]), "epochs": cfg.epochs,
                                       "lr": cfg.lr, "batch_size": cfg.batch_size, "threads": cfg.threads})
    original = original_frames(recipe, cfg.original_frames, request.work / "original_data.npz", request.progress)
    failures = concat([export_frames(f) for f in request.failures])
    if not len(failures):
        raise UserInputError(f"round {request.round}: the failure exports hold no frame to retrain on")
    data = concat([original] + [failures] * cfg.failure_repeat)

    torch.set_num_threads(cfg.threads)
    init_ss, shuffle_ss = np.random.SeedSequence([request.seed, request.round, 4099]).spawn(2)
    torch.manual_seed(int(init_ss.generate_state(1)[0]))
    rng = np.random.default_rng(shuffle_ss)
    mcfg = DetectorModelConfig.from_dict(dict(ckpt["model_config"]))
    # Module.to takes memory_format at run time, but torch's overloads for it omit the keyword
    net = VehicleDetectorNet(mcfg).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    net.load_state_dict(ckpt["state_dict"])
    teacher = None
    if cfg.distill > 0:
        teacher = VehicleDetectorNet(mcfg).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        teacher.load_state_dict(ckpt["state_dict"])
        teacher.eval()
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=train_cfg.weight_decay)
    t0 = time.perf_counter()

    def batch_loss(idx: np.ndarray) -> Any:
        x, t = training_batch(data, idx, train_cfg, rng)
        out = net(x)
        loss, _ = detector_loss(out, t, train_cfg)
        if teacher is not None:
            loss = loss + cfg.distill * _distillation(out, teacher, x, idx < len(original))
        return loss

    history = train_epochs(opt, list(net.parameters()), len(data), cfg.epochs, cfg.batch_size, cfg.lr, rng,
                           batch_loss, on_epoch=lambda: _train_frozen_norms(net),
                           desc=f"round {request.round}: fine-tune" if request.progress else None)
    net.eval()
    threshold, validation = float(ckpt["score_threshold"]), None
    if cfg.repick_threshold:
        threshold, validation = _repick_threshold(net, ckpt, recipe, train_cfg, cfg, request)
    state = {k: v.detach().to(torch.float32).contiguous().clone() if v.is_floating_point() else v.clone()
             for k, v in net.state_dict().items()}
    finetune = {"round": request.round, "seed": request.seed, "config": dataclasses.asdict(cfg),
                "base_weights_sha256": file_sha256(request.weights), "original_frames": len(original),
                "original_sha256": dataset_sha256(original), "failure_frames": len(failures),
                "failure_sha256": dataset_sha256(failures),
                # relative to the harden folder: a round resumed in a moved folder writes the same checkpoint
                "failure_exports": [relative_to(f, request.work) for f in request.failures],
                "history": history, "score_threshold": threshold, "validation": validation}
    meta = dict(ckpt.get("metadata", {}))
    out_ckpt = {**ckpt, "state_dict": state, "score_threshold": threshold,
                "metadata": {**meta, "genesis_rl_version": genesis_rl.__version__,
                             "finetunes": [*meta.get("finetunes", []), finetune]}}
    request.out.mkdir(parents=True, exist_ok=True)
    path = request.out / WEIGHTS_NAME
    # torch names a file's records after the file, here atomic_write's temporary: through a buffer the same
    # weights give the same bytes (a resumed round is checked by its hash)
    buffer = io.BytesIO()
    torch.save(out_ckpt, buffer)
    atomic_write(path, lambda p: p.write_bytes(buffer.getvalue()))
    atomic_write_json(request.out / METRICS_NAME, {"format": ckpt["format"], "weights": WEIGHTS_NAME,
                                                   "score_threshold": threshold,
                                                   "model_config": ckpt["model_config"], "train_config": recipe,
                                                   "finetune": finetune,
                                                   "seconds": round(time.perf_counter() - t0, 1)}, indent=2)
    return path
