"""The training configuration: [env], [ppo], [sac], [recurrent] and [train] tables; ``configs/paper.toml`` spells
out the paper's values with units. ``train.algorithm`` picks the learner: PPO (the paper's), SAC, or PPO with an
LSTM (``recurrent_ppo``: sb3-contrib's RecurrentPPO, the [ppo] table's settings and the [recurrent] table's)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from genesis_rl.core import limits, ranges
from genesis_rl.core.config import dump_toml, from_mapping, read_toml, to_mapping
from genesis_rl.core.errors import UserInputError
from genesis_rl.env.genesis_env import EnvConfig

_R = ranges.Ranged
#: a rollout or batch of 2**20 image steps is about 20 GB: beyond that a run cannot fit in memory
_BIG_COUNT = 2**20
#: the physical range of every numeric key of [ppo], [sac] and [train] (docs/reliability.md)
PPO_RANGES: dict[str, ranges.Ranged] = {
    "learning_rate": _R(1e-8, 1.0, note="SB3's 3e-4"),
    "n_steps": _R(2, _BIG_COUNT, "steps", integer=True),
    "batch_size": _R(2, _BIG_COUNT, "steps", integer=True),
    "n_epochs": _R(1, 1000, integer=True),
    "gamma": _R(1e-6, 1.0),
    "gae_lambda": _R(1e-6, 1.0),
    "clip_range": _R(1e-6, 10.0),
    "ent_coef": _R(0.0, 100.0),
    "vf_coef": _R(0.0, 100.0),
    "max_grad_norm": _R(1e-6, 1e6),
    "log_std_init": _R(-5.0, 2.0, note="std e^-5..e^2"),
}
SAC_RANGES: dict[str, ranges.Ranged] = {
    "learning_rate": _R(1e-8, 1.0, note="SB3's 3e-4"),
    "buffer_size": _R(1, 10_000_000, "transitions", integer=True),  # 10M image transitions: ~60 GB
    "learning_starts": _R(0, limits.TIMESTEPS.default, "steps", integer=True),
    "batch_size": _R(1, _BIG_COUNT, "transitions", integer=True),
    "tau": _R(1e-6, 1.0),
    "gamma": _R(1e-6, 1.0),
    "train_freq": _R(1, 1_000_000, "steps", integer=True),
    "gradient_steps": _R(1, 10_000, integer=True),
}
#: SAC's entropy coefficient X in 'X' or 'auto_X'
SAC_ENT_COEF = _R(1e-6, 100.0)
TRAIN_RANGES: dict[str, ranges.Ranged] = {
    "total_timesteps": _R(1, 2**62, "env steps", integer=True),  # and at most limits.TIMESTEPS
    "envs": _R(1, 64, "processes", integer=True),
    "seed": _R(0, 2**32 - 1, integer=True, note="gymnasium's and SB3's seeding limit"),
    "checkpoint_every": _R(1, 2**62, "env steps", integer=True),
    "torch_threads": _R(0, 1024, "threads", integer=True, note="0: torch's default"),
}


def _check_types(section: str, obj: object, table: dict[str, ranges.Ranged]) -> None:
    """Before the checks below compare them: each value an int (integer keys) or a number, never a bool."""
    for k, rng in table.items():
        ranges.check_type(getattr(obj, k), f"{section}.{k}", rng)


def _check_ranges(section: str, obj: object, table: dict[str, ranges.Ranged]) -> None:
    """After them: finite and within the key's physical range (what the checks above let through)."""
    for k, rng in table.items():
        rng.check(getattr(obj, k), f"{section}.{k}")


@dataclass(frozen=True)
class PPOConfig:
    """Stable-Baselines3 PPO settings (SB3's defaults, and the paper's rollout of 2048 steps)."""

    learning_rate: float = 3e-4
    n_steps: int = 2048  # steps per policy update over all envs together (the paper: 4 episodes of 512)
    batch_size: int = 64
    n_epochs: int = 10
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    log_std_init: float = 0.0  # initial log standard deviation of the Gaussian policy (SB3's default 0: std 1)
    device: str = "auto"  # torch device for the policy: auto, cpu, cuda

    def __post_init__(self) -> None:
        _check_types("ppo", self, PPO_RANGES)
        if self.n_steps < 2 or self.batch_size < 2:
            raise UserInputError(f"ppo.n_steps = {self.n_steps} and ppo.batch_size = {self.batch_size} must be >= 2")
        limits.BUFFER.check(self.n_steps, "ppo.n_steps")  # the rollout buffer is allocated whole, at once
        if not 0 < self.learning_rate < 1:
            raise UserInputError(f"ppo.learning_rate = {self.learning_rate} must be in (0, 1)")
        if not (0 < self.gamma <= 1 and 0 < self.gae_lambda <= 1):
            raise UserInputError("ppo.gamma and ppo.gae_lambda must be in (0, 1]")
        if not -5.0 <= self.log_std_init <= 2.0:
            raise UserInputError(f"ppo.log_std_init = {self.log_std_init} must be in -5..2 (std e^-5..e^2)")
        if self.n_epochs < 1:
            raise UserInputError(f"ppo.n_epochs = {self.n_epochs} must be >= 1")
        for k in ("clip_range", "max_grad_norm"):
            if not getattr(self, k) > 0:
                raise UserInputError(f"ppo.{k} = {getattr(self, k)} must be > 0")
        for k in ("vf_coef", "ent_coef"):
            if not getattr(self, k) >= 0:
                raise UserInputError(f"ppo.{k} = {getattr(self, k)} must be >= 0")
        _check_ranges("ppo", self, PPO_RANGES)
        check_device("ppo", self.device)

    def check_device_present(self) -> None:
        check_device_present("ppo", self.device)


def check_device(section: str, device: str) -> None:
    kind, _, index = device.partition(":")
    if kind not in ("auto", "cpu", "cuda", "mps") or (index and not (kind == "cuda" and index.isdigit())):
        raise UserInputError(f"{section}.device = '{device}'; allowed: auto, cpu, cuda, cuda:N, mps")


def check_device_present(section: str, device: str) -> None:
    """Refuse a device this machine lacks: SB3 would fall back to the CPU without a word, and a run meant
    for a GPU would take hours instead of minutes. ("auto" takes the GPU when there is one.)"""
    import torch  # local: start-up cost; checked only when training starts

    kind, _, index = device.partition(":")
    fix = f'set {section}.device = "auto" (the GPU when there is one) or "cpu"'
    if kind == "cuda":
        if not torch.cuda.is_available():
            raise UserInputError(f"{section}.device = '{device}' but torch.cuda.is_available() = False on this "
                                 f"machine (torch {torch.__version__}, built for CUDA {torch.version.cuda}); {fix}")
        if index and int(index) >= torch.cuda.device_count():
            raise UserInputError(f"{section}.device = '{device}' but this machine has {torch.cuda.device_count()} "
                                 f"CUDA device(s), 0..{torch.cuda.device_count() - 1}; {fix}")
    if kind == "mps" and not torch.backends.mps.is_available():
        raise UserInputError(f"{section}.device = 'mps' but torch.backends.mps.is_available() = False; {fix}")


@dataclass(frozen=True)
class SACConfig:
    """Stable-Baselines3 SAC settings (SB3's defaults but a shorter warm-up and a buffer that holds the
    paper's whole budget). SAC's policy is a tanh-squashed Gaussian: its mean never sits beyond the action
    bounds, and a critic that values each action reuses every step many times."""

    learning_rate: float = 3e-4
    buffer_size: int = 100_000  # transitions kept (40,960 feature transitions take ~25 MB; images ~0.6 GB)
    learning_starts: int = 1024  # env steps of the random policy before the first update
    batch_size: int = 256
    tau: float = 0.005
    gamma: float = 0.99
    train_freq: int = 1  # env steps (per env) between updates
    gradient_steps: int = 1  # updates each time
    ent_coef: str = "auto"  # "auto" (learned, from 1), "auto_X" (learned, from X) or a fixed number
    net_arch: tuple[int, ...] = (256, 256)  # hidden layers of the actor and of each critic (SB3's default)
    device: str = "auto"

    def __post_init__(self) -> None:
        _check_types("sac", self, SAC_RANGES)
        if not 0 < self.learning_rate < 1:
            raise UserInputError(f"sac.learning_rate = {self.learning_rate} must be in (0, 1)")
        if not 0 < self.gamma <= 1 or not 0 < self.tau <= 1:
            raise UserInputError("sac.gamma and sac.tau must be in (0, 1]")
        for k in ("buffer_size", "batch_size", "train_freq", "gradient_steps"):
            if getattr(self, k) < 1:
                raise UserInputError(f"sac.{k} = {getattr(self, k)} must be >= 1")
        limits.BUFFER.check(self.buffer_size, "sac.buffer_size")  # the replay buffer is allocated whole, at once
        widths = self.net_arch
        if not (isinstance(widths, tuple | list) and 1 <= len(widths) <= 16
                and all(isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= 4096 for n in widths)):
            shown = list(widths) if isinstance(widths, tuple | list) else widths
            raise UserInputError(f"sac.net_arch = {shown!r}: expected 1 or more layer widths in 1..4096 "
                                 "(at most 16 layers)")
        if self.learning_starts < 0:
            raise UserInputError(f"sac.learning_starts = {self.learning_starts} must be >= 0")
        if not isinstance(self.ent_coef, str):
            raise UserInputError(f"sac.ent_coef = {self.ent_coef!r}; allowed: 'auto', 'auto_X' or 'X' (a string) "
                                 f"with X in {SAC_ENT_COEF.bounds()}")
        if self.ent_coef != "auto":
            number = self.ent_coef.removeprefix("auto_")
            try:
                x = float(number)  # 'inf' and '1e308' parse: refused by the range
                ok = math.isfinite(x) and SAC_ENT_COEF.low <= x <= SAC_ENT_COEF.high
            except ValueError:
                ok = False
        else:
            ok = True
        if not ok:
            raise UserInputError(f"sac.ent_coef = '{self.ent_coef}'; allowed: 'auto', 'auto_X' or 'X' with X in "
                                 f"{SAC_ENT_COEF.bounds()}")
        _check_ranges("sac", self, SAC_RANGES)
        check_device("sac", self.device)

    def sb3_ent_coef(self) -> str | float:
        return self.ent_coef if self.ent_coef.startswith("auto") else float(self.ent_coef)


#: the LSTM's size: a wider or deeper one than this is far beyond what a few knobs and gaps need
RECURRENT_RANGES: dict[str, ranges.Ranged] = {
    "lstm_hidden_size": _R(1, 1024, "units", integer=True),
    "n_lstm_layers": _R(1, 8, "layers", integer=True),
}


@dataclass(frozen=True)
class RecurrentConfig:
    """The memory of ``train.algorithm = "recurrent_ppo"`` (sb3-contrib's RecurrentPPO; its other settings are
    the [ppo] table's). An LSTM carries what the agent saw earlier in the episode (the stutter that began
    a second ago, the gap that has been closing) where a stack of the last few observations forgets it."""

    lstm_hidden_size: int = 64  # sb3-contrib's default is 256; 64 matches the policy's [64, 64] layers
    n_lstm_layers: int = 1
    enable_critic_lstm: bool = True  # the value function has its own LSTM (sb3-contrib's default)

    def __post_init__(self) -> None:
        _check_types("recurrent", self, RECURRENT_RANGES)
        if not isinstance(self.enable_critic_lstm, bool):
            raise UserInputError(f"recurrent.enable_critic_lstm = {self.enable_critic_lstm!r}; allowed: true, false")
        _check_ranges("recurrent", self, RECURRENT_RANGES)


ALGORITHMS = ("ppo", "sac", "recurrent_ppo")
#: the learners that collect PPO's rollouts, with the [ppo] table's settings
PPO_FAMILY = ("ppo", "recurrent_ppo")


@dataclass(frozen=True)
class TrainConfig:
    algorithm: str = "ppo"  # the learner: ppo (the paper's; [ppo]), sac ([sac]) or recurrent_ppo ([ppo], [recurrent])
    total_timesteps: int = 40960  # env steps (the paper: 40,960 = 20 updates of 2048)
    envs: int = 1  # parallel environments, each in its own process when > 1
    seed: int = 0  # seeds the envs' scene draws, the policy's initialisation and its sampling
    checkpoint_every: int = 2048  # env steps between checkpoints
    torch_threads: int = 0  # torch threads in the trainer (0: torch's default; one for SAC's updates)

    def __post_init__(self) -> None:
        if self.algorithm not in ALGORITHMS:
            raise UserInputError(f"train.algorithm = '{self.algorithm}'; allowed: {', '.join(ALGORITHMS)}")
        _check_types("train", self, TRAIN_RANGES)
        if self.total_timesteps < 1:
            raise UserInputError(f"train.total_timesteps = {self.total_timesteps} must be >= 1")
        limits.TIMESTEPS.check(self.total_timesteps, "train.total_timesteps")
        if not 1 <= self.envs <= 64:
            raise UserInputError(f"train.envs = {self.envs} must be in 1..64")
        if self.checkpoint_every < 1:
            raise UserInputError(f"train.checkpoint_every = {self.checkpoint_every} must be >= 1")
        if not 0 <= self.seed < 2**32:  # gymnasium's and SB3's seeding limit
            raise UserInputError(f"train.seed = {self.seed}; allowed: an integer in 0..{2**32 - 1}")
        if self.torch_threads < 0:
            raise UserInputError(f"train.torch_threads = {self.torch_threads} must be >= 0 (0: torch's default)")
        _check_ranges("train", self, TRAIN_RANGES)


@dataclass(frozen=True)
class RunConfig:
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    sac: SACConfig = field(default_factory=SACConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    recurrent: RecurrentConfig = field(default_factory=RecurrentConfig)

    def __post_init__(self) -> None:
        # each env collects the same share of a PPO update's rollout
        if self.train.algorithm in PPO_FAMILY and self.ppo.n_steps % self.train.envs:
            raise UserInputError(f"ppo.n_steps = {self.ppo.n_steps} must be a multiple of train.envs = "
                                 f"{self.train.envs}")

    def to_toml(self) -> str:
        """The resolved config; [recurrent] only for a recurrent learner, so every other run's file reads as
        before."""
        tables = {"env": to_mapping(self.env), "ppo": to_mapping(self.ppo), "sac": to_mapping(self.sac),
                  "train": to_mapping(self.train)}
        if self.train.algorithm == "recurrent_ppo":
            tables["recurrent"] = to_mapping(self.recurrent)
        return dump_toml(tables)

    @property
    def device(self) -> str:
        """The torch device of the chosen learner."""
        return self.sac.device if self.train.algorithm == "sac" else self.ppo.device

    @property
    def device_section(self) -> str:
        """The table that sets the learner's device (recurrent_ppo's is [ppo])."""
        return "sac" if self.train.algorithm == "sac" else "ppo"


def load_run_config(path: str | Path | None, overrides: dict[str, dict[str, Any]] | None = None) -> RunConfig:
    """Read a config file (None: all defaults) and apply per-section overrides from the command line."""
    data = read_toml(path) if path is not None else {}
    unknown = sorted(set(data) - {"env", "ppo", "sac", "train", "recurrent"})
    if unknown:
        raise UserInputError(f"unknown table(s) {unknown} in '{path}'; allowed: env, ppo, sac, train, recurrent")
    for section, values in (overrides or {}).items():
        data.setdefault(section, {}).update(values)
    algorithm = (data.get("train") or {}).get("algorithm", TrainConfig.algorithm)
    if data.get("recurrent") and algorithm != "recurrent_ppo":  # e.g. a recurrent config run with --algorithm ppo
        warnings.warn(f"the [recurrent] table is ignored: train.algorithm = {algorithm!r} has no LSTM", stacklevel=2)
    return RunConfig(
        env=from_mapping(EnvConfig, data.get("env"), "env"),
        ppo=from_mapping(PPOConfig, data.get("ppo"), "ppo"),
        sac=from_mapping(SACConfig, data.get("sac"), "sac"),
        train=from_mapping(TrainConfig, data.get("train"), "train"),
        recurrent=from_mapping(RecurrentConfig, data.get("recurrent"), "recurrent"),
    )
