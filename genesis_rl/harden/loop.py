"""What both built-in fine-tunes share: how their settings are read, the training loop over shuffled batches with a
cosine learning rate, and how they record paths inside the harden folder."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from genesis_rl.core.errors import UserInputError

Config = TypeVar("Config")


def finetune_config(config: type[Config], options: Mapping[str, Any], kind: str) -> Config:
    """``config(**options)``: a fine-tune's settings, a setting it does not know refused by name (``kind`` names
    the fine-tune), bad values by the config's own checks."""
    known = {f.name for f in dataclasses.fields(config)}  # type: ignore[arg-type]  # a dataclass type
    unknown = sorted(set(options) - known)
    if unknown:
        raise UserInputError(f"harden finetune: unknown setting(s) {unknown} for {kind}; allowed: "
                             f"{', '.join(sorted(known))}")
    return config(**options)


def train_epochs(opt: Any, params: list[Any], frames: int, epochs: int, batch_size: int, lr: float,
                 rng: np.random.Generator, batch_loss: Callable[[np.ndarray], Any],
                 on_epoch: Callable[[], None] | None = None, desc: str | None = None) -> list[dict[str, Any]]:
    """The fine-tunes' loop: ``epochs`` passes over ``frames`` frames in an order ``rng`` shuffles, batches of
    sorted indices, the cosine learning rate, gradients clipped at norm 10; ``batch_loss(indices)`` is a batch's
    loss, ``on_epoch`` runs before each pass, ``desc`` names a progress bar. Returns each epoch's mean loss."""
    import torch

    per_epoch = math.ceil(frames / batch_size)
    total = per_epoch * epochs
    bar = None
    if desc is not None:
        from tqdm import tqdm

        bar = tqdm(total=total, desc=desc, unit="batch")
    history, step = [], 0
    try:
        for epoch in range(epochs):
            if on_epoch is not None:
                on_epoch()
            order = rng.permutation(frames)
            loss_sum = 0.0
            for s in range(0, len(order), batch_size):
                idx = np.sort(order[s : s + batch_size])
                loss = batch_loss(idx)
                for g in opt.param_groups:
                    g["lr"] = cosine_lr(lr, step, total)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(params, 10.0)
                opt.step()
                step += 1
                loss_sum += float(loss.detach())
                if bar is not None:
                    bar.update(1)
            history.append({"epoch": epoch + 1, "loss": round(loss_sum / per_epoch, 4)})
    finally:
        if bar is not None:
            bar.close()
    return history


def cosine_lr(base: float, step: int, total: int) -> float:
    """The fine-tunes' learning rate at ``step`` of ``total``: cosine decay from ``base`` to 2 % of it."""
    return base * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * step / total)))


def relative_to(path: Path, root: Path) -> str:
    """``path`` relative to ``root`` when inside it (a moved harden folder's records stay true), else as given."""
    try:
        return Path(path).resolve().relative_to(Path(root).resolve()).as_posix()
    except ValueError:
        return str(path)
