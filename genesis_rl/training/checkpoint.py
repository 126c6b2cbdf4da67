"""Checkpoints that resume a training run exactly.

A checkpoint is taken at a rollout boundary, after that rollout's PPO update, and holds everything the next
rollout depends on: the policy and its optimizer state (``step_N.zip``, SB3's own format, which also keeps
the last observation and the step counters), and in ``step_N.state.json`` the trainer's random generators
(torch, numpy, Python), every env's generator, the scene, episode seed and actions of the episode each env is
in (the lite simulator rebuilds an episode exactly from them), the per-episode sums of the episode-metrics
callback and the number of rows in ``episodes.csv``. ``step_N.sb3.npz`` keeps what SB3 itself pickles into
the zip and a resumed run needs (the last observation and episode starts), so that nothing is unpickled on
resume (training/safe_load.py). An off-policy learner (SAC) also keeps its replay buffer (``step_N.replay.npz``,
plain arrays; only the newest is kept, it is the largest file). ``last.json`` names the newest complete
checkpoint and is written last, so a crash while checkpointing leaves the previous one in charge.
Checkpoints of genesis-rl 0.10.0 and before (no ``.sb3.npz``, a ``.replay.pkl`` buffer) resume only with
``--trust-pickle``. SIGINT and SIGTERM wait until a checkpoint is whole (``signals.deferred_signals``).
"""

from __future__ import annotations

import base64
import csv
import hashlib
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, SupportsFloat, cast

import gymnasium as gym
import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json
from genesis_rl.core.parsing import read_json
from genesis_rl.core.signals import deferred_signals
from genesis_rl.core.trust import pickle_trusted
from genesis_rl.training.safe_load import (
    TRUST_HINT,
    load_model,
    read_replay_buffer,
    read_sb3_state,
    sb3_state_path,
    write_replay_buffer,
    write_sb3_state,
)

if TYPE_CHECKING:
    from genesis_rl.env.genesis_env import GenesisEnv
    from genesis_rl.training.config import RunConfig

CHECKPOINTS = "checkpoints"
STATE_FORMAT = 1


def _digest(obs: Any) -> str:
    h = hashlib.sha256()
    for part in (obs.values() if isinstance(obs, dict) else [obs]):
        h.update(np.ascontiguousarray(part).tobytes())
    return h.hexdigest()


class EpisodeLog(gym.Wrapper):
    """Remembers what rebuilds the env's current episode in a fresh process: its scene and episode seed, the
    actions taken so far, and a digest of the last observation (to prove the rebuild exact)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self._actions: list[list[float]] = []
        self._obs_digest = ""

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        obs, info = self.env.reset(**kwargs)
        self._actions = []
        self._obs_digest = _digest(obs)
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._actions.append(np.asarray(action).tolist())
        self._obs_digest = _digest(obs)
        return obs, reward, terminated, truncated, info

    def resume_state(self) -> dict[str, Any]:
        u = cast("GenesisEnv", self.unwrapped)  # the env this wrapper is put around
        return {"scene": int(u.scene_index), "episode_seed": int(u.episode_seed), "actions": self._actions,
                "action_dtype": str(self.action_space.dtype), "obs_sha256": self._obs_digest,
                "np_random": u.np_random.bit_generator.state}

    def restore(self, state: dict[str, Any]) -> str | None:
        """Replay the saved episode from its start, then put the env's generator where it was. Returns what
        went wrong, or None (a message, not an exception: the env may live in a subprocess)."""
        self.reset(options={"scene": state["scene"], "episode_seed": state["episode_seed"]})
        for action in state["actions"]:
            self.step(np.asarray(action, dtype=state["action_dtype"]))
        if self._obs_digest != state["obs_sha256"]:
            return (f"scene {state['scene']} replayed to another observation than the checkpoint's (a simulator "
                    "that does not replay exactly, e.g. CARLA, or another package version)")
        self.unwrapped.np_random.bit_generator.state = state["np_random"]
        return None


def _trainer_rng() -> dict[str, Any]:
    import torch

    version, internal, gauss = random.getstate()
    # SB3 shuffles minibatches with the global generator; an MT19937, so its state is the legacy tuple
    legacy = cast("tuple[str, np.ndarray, int, int, float]", np.random.get_state())  # noqa: NPY002
    name, keys, pos, has_gauss, cached = legacy
    state = {"python": [version, list(internal), gauss],
             "numpy": [name, keys.tolist(), int(pos), int(has_gauss), float(cached)],
             "torch": base64.b64encode(torch.get_rng_state().numpy().tobytes()).decode()}
    if torch.cuda.is_available():
        state["cuda"] = [base64.b64encode(s.numpy().tobytes()).decode() for s in torch.cuda.get_rng_state_all()]
    return state


def _set_trainer_rng(state: dict[str, Any]) -> None:
    import torch

    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))  # noqa: NPY002
    torch.set_rng_state(torch.from_numpy(np.frombuffer(base64.b64decode(state["torch"]), dtype=np.uint8).copy()))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([torch.from_numpy(np.frombuffer(base64.b64decode(s), dtype=np.uint8).copy())
                                      for s in state["cuda"]])


def csv_rows(path: Path) -> int:
    """Data rows of ``episodes.csv`` (0 when it is missing)."""
    if not path.is_file():
        return 0
    from genesis_rl.core.parsing import csv_rows as rows_of

    return max(0, sum(1 for _ in rows_of(path, "episode log", encoding="utf-8", limit=None)) - 1)


def truncate_csv(path: Path, rows: int) -> None:
    """Keep the header and the first ``rows`` rows: rows written after the checkpoint are trained again."""
    if not path.is_file():
        return
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            lines = list(csv.reader(fh))
    except (UnicodeDecodeError, csv.Error) as err:  # not the checkpoint's damage: name the file that is
        raise UserInputError(f"--resume: the episode log '{path}' is damaged ({err}); move it away to resume "
                             "without it, or start the run again with --force") from None
    if len(lines) - 1 > rows:
        def write(p: Path) -> None:
            with p.open("w", newline="") as fh:
                csv.writer(fh).writerows(lines[:rows + 1])

        atomic_write(path, write)


@deferred_signals()  # one unit: Ctrl-C or SIGTERM during it takes effect once last.json names the new one
def save_checkpoint(run: Path, model: Any, steps: int, episode_sums: dict[int, dict[str, Any]]) -> None:
    """``step_N.zip`` + ``step_N.state.json``, a copy as ``last.zip``, then ``last.json`` naming N."""
    ck = run / CHECKPOINTS
    env = model.get_env()
    state = {"format": STATE_FORMAT, "timesteps": int(steps), "trainer_rng": _trainer_rng(),
             "envs": env.env_method("resume_state"),
             "episode_sums": {str(i): a for i, a in episode_sums.items()},
             "episodes_csv_rows": csv_rows(run / "episodes.csv")}
    atomic_write(ck / f"step_{steps:08d}.zip", lambda p: model.save(p))
    atomic_write(sb3_state_path(ck / f"step_{steps:08d}.zip"), lambda p: write_sb3_state(p, model))
    replay = replay_path(ck, steps)
    if hasattr(model, "replay_buffer"):
        atomic_write(replay, lambda p: write_replay_buffer(p, model.replay_buffer))
    atomic_write_json(ck / f"step_{steps:08d}.state.json", state)
    atomic_write(ck / "last.zip", lambda p: model.save(p))
    atomic_write_json(ck / "last.json", {"timesteps": int(steps), "time": time.time(),
                                         "checkpoint": f"step_{steps:08d}.zip",
                                         "state": f"step_{steps:08d}.state.json"})
    for pattern in ("step_*.replay.npz", "step_*.replay.pkl"):  # last.json names the new one now: the older
        for old in ck.glob(pattern):                                # buffers can go
            if old != replay:
                old.unlink(missing_ok=True)


def replay_path(ck: Path, steps: int) -> Path:
    return ck / f"step_{steps:08d}.replay.npz"


def _pickled_replay_path(ck: Path, steps: int) -> Path:
    """Where genesis-rl 0.10.0 and before kept SAC's replay buffer (SB3's pickle)."""
    return ck / f"step_{steps:08d}.replay.pkl"


@dataclass
class Resumed:
    model: Any
    steps: int
    episode_sums: dict[int, dict[str, Any]]


def _damaged(path: Path, what: str) -> UserInputError:
    return UserInputError(f"--resume: checkpoint file '{path}' is damaged ({what}); start the run again with --force")


def read_last(run: Path, max_steps: int) -> tuple[int, Path, Path | None]:
    """The newest checkpoint's step count, model file and state file, each checked: ``0 <= N <= max_steps``
    and the files it names present. ``state`` is None for a checkpoint written by genesis-rl 0.4.0."""
    ck = run / CHECKPOINTS
    meta_path = ck / "last.json"
    if not meta_path.is_file():
        raise UserInputError(f"--resume: run '{run}' has no complete checkpoint ({meta_path} missing); start it "
                             "again with --force")
    try:
        meta = read_json(meta_path, "checkpoint file")
    except UserInputError:
        raise _damaged(meta_path, "expected JSON with an integer 'timesteps'") from None
    steps = meta.get("timesteps") if isinstance(meta, dict) else None
    if not isinstance(steps, int) or isinstance(steps, bool):
        raise _damaged(meta_path, "expected JSON with an integer 'timesteps'")
    if not 0 <= steps <= max_steps:
        raise _damaged(meta_path, f"timesteps = {steps}; allowed: 0..{max_steps}, the run's train.total_timesteps "
                                  "rounded up to whole rollouts")
    if "state" not in meta:  # genesis-rl 0.4.0: last.zip only
        model = ck / "last.zip"
        if not model.is_file():
            raise UserInputError(f"--resume: run '{run}' has no complete checkpoint ({model} missing); start it "
                                 "again with --force")
        return steps, model, None
    names = (meta.get("checkpoint"), meta.get("state"))
    expected = (f"step_{steps:08d}.zip", f"step_{steps:08d}.state.json")
    if names != expected:
        raise _damaged(meta_path, f"it names {names[0]!r} and {names[1]!r}; expected {expected[0]!r} and "
                                  f"{expected[1]!r} for timesteps = {steps}")
    missing = [str(ck / n) for n in names if not (ck / n).is_file()]
    if missing:
        raise UserInputError(f"--resume: run '{run}' has no complete checkpoint ({', '.join(missing)} missing); "
                             "start it again with --force")
    return steps, ck / names[0], ck / names[1]


def load_checkpoint(run: Path, env: Any, device: str, max_steps: int, cfg: RunConfig) -> Resumed:
    """Reload the newest checkpoint into ``env``: model, optimizer, replay buffer (SAC), random generators and
    each env's episode. Nothing is unpickled (training/safe_load.py) unless the command has --trust-pickle,
    which a checkpoint of genesis-rl 0.10.0 or before needs."""
    steps, model_path, state_path = read_last(run, max_steps)
    state = None
    if state_path is not None:
        state = read_json(state_path, "checkpoint state")
        if not isinstance(state, dict) or type(state.get("timesteps")) is not int or state["timesteps"] != steps \
                or type(state.get("format")) is not int or state["format"] != STATE_FORMAT:  # JSON's true == 1
            raise _damaged(state_path, f"expected format {STATE_FORMAT} for timesteps = {steps}")
        if not isinstance(state.get("envs"), list) or len(state["envs"]) != env.num_envs:
            raise _damaged(state_path, f"expected the state of {env.num_envs} env(s)")
    trust = pickle_trusted()
    ck = model_path.parent
    sb3_state = None
    recurrent = cfg.train.algorithm == "recurrent_ppo"  # its LSTM memory is in the .sb3.npz alone, trusted or not
    if state is not None and (not trust or recurrent):  # 0.4.0 checkpoints hold no observation: envs are reset
        sb3_path = sb3_state_path(model_path)
        if not sb3_path.is_file():
            if recurrent:
                raise UserInputError(f"--resume: the checkpoint in '{run}' has no {sb3_path.name}, which keeps the "
                                     "recurrent policy's memory; start the run again with --force")
            raise UserInputError(f"--resume: the checkpoint in '{run}' was written by genesis-rl 0.10.0 or before "
                                 f"and keeps its last observation only pickled inside '{model_path.name}' (no "
                                 f"{sb3_path.name}); {TRUST_HINT}")
        sb3_state = read_sb3_state(sb3_path, cfg, env.num_envs)
    replay = replay_path(ck, steps)
    if cfg.train.algorithm == "sac" and not replay.is_file():
        pickled = _pickled_replay_path(ck, steps)
        if not pickled.is_file():
            raise UserInputError(f"--resume: run '{run}' has no complete checkpoint ({replay} missing); start "
                                 "it again with --force")
        if not trust:
            raise UserInputError(f"--resume: the checkpoint in '{run}' keeps SAC's replay buffer as a pickle "
                                 f"('{pickled.name}', genesis-rl 0.10.0 and before); {TRUST_HINT}")
        replay = pickled
    # force_reset=False keeps the checkpoint's last observation: the envs are rebuilt below, not reset
    model: Any = load_model(model_path, cfg, env=env, device=device, resume_state=sb3_state,
                            force_reset=state is None, what="--resume", trust_pickle=trust)
    if cfg.train.algorithm == "sac":
        if replay.suffix == ".pkl":
            try:
                model.load_replay_buffer(replay)
            except Exception as err:  # noqa: BLE001 - a corrupt pickle raises many kinds
                raise UserInputError(f"--resume: replay buffer '{replay}' cannot be loaded: {err}") from None
        else:
            read_replay_buffer(replay, model.replay_buffer)
    model.num_timesteps = steps
    if state is None:
        print(f"genesis-rl train: the checkpoint in '{run}' was written by genesis-rl 0.4.0 and holds no trainer "
              "state; the run continues, but will not match an uninterrupted one", flush=True)
        return Resumed(model, steps, {})
    try:
        truncate_csv(run / "episodes.csv", int(state["episodes_csv_rows"]))
        for i, env_state in enumerate(state["envs"]):
            problem = env.env_method("restore", env_state, indices=[i])[0]
            if problem:
                raise UserInputError(f"--resume: env {i}: {problem}; start the run again with --force")
        _set_trainer_rng(state["trainer_rng"])  # last: PPO.load reseeded them, and replaying may draw
        sums = {int(i): a for i, a in state["episode_sums"].items()}
    except UserInputError:  # a ValueError, but one that names its own file
        raise
    except (KeyError, TypeError, ValueError, IndexError) as err:
        assert state_path is not None  # the state was read from it
        raise _damaged(state_path, f"{type(err).__name__}: {err}") from None
    return Resumed(model, steps, sums)
