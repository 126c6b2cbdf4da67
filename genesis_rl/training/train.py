"""``genesis-rl train``: SB3 PPO (or SAC, or sb3-contrib's RecurrentPPO) against GenesisEnv, with checkpoints,
resume, TensorBoard and a progress bar.

The run folder keeps everything needed to trust and reuse the agent: the resolved config, the scene
catalog it trained on, seeds, package version and git commit (``run.json``), checkpoints with their step
counts, per-episode metrics (``episodes.csv``), TensorBoard logs (``tb/``) and the final ``agent.zip``.
"""

from __future__ import annotations

import csv
import shutil
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv
from tqdm import tqdm

from genesis_rl import __version__
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json, atomic_write_text
from genesis_rl.core.provenance import git_commit
from genesis_rl.core.signals import deferred_signals, resume_hint, set_resume_hint
from genesis_rl.distributed.ray_cluster import RayWorkersLost
from genesis_rl.distributed.settings import ExecutorSettings
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.env.observation import sb3_policy
from genesis_rl.loop.rules.reward import RewardConfig
from genesis_rl.sim.backends import catalog_or_generate
from genesis_rl.training.checkpoint import CHECKPOINTS, EpisodeLog, load_checkpoint, read_last, save_checkpoint
from genesis_rl.training.config import PPO_FAMILY, RunConfig, check_device_present, load_run_config
from genesis_rl.training.pinning import adopt_pins, check_run, current_pins, write_pins
from genesis_rl.training.safe_load import learner_class, learner_kwargs, policy_name
from genesis_rl.training.throughput import RolloutThreads


def _make_env(config_dict: dict[str, Any], rank: int, seed: int, torch_threads: int,  # noqa: ANN202
              subprocess: bool = False):
    def thunk():  # noqa: ANN202
        if subprocess:  # Ctrl-C reaches every process of the command: it is the trainer's, which closes the envs
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        if torch_threads:
            torch.set_num_threads(torch_threads)
        env = GenesisEnv(EnvConfig(**config_dict))
        try:
            env.reset(seed=seed + rank)
        except BaseException:
            # the first episode failed to set up (e.g. a system that refuses the map): release the simulator
            # now, or a CARLA server stays in synchronous mode with the scene's actors and the next run fails
            env.close()
            raise
        return EpisodeLog(Monitor(env))

    return thunk


def build_vec_env(cfg: RunConfig, catalog_path: Path, scale: ExecutorSettings | None = None):  # noqa: ANN201
    """The training envs: in this process (one env), in subprocesses, or in Ray actors (``scale.kind`` ray);
    env i drives ``scale``'s server i when the backend is CARLA. The same seeds give the same rollouts."""
    scale = scale or ExecutorSettings(workers=cfg.train.envs, what="--envs")
    env_cfg = replace(cfg.env, catalog=str(catalog_path))
    d = asdict(env_cfg)
    d["reward"] = RewardConfig(**d["reward"])
    n = cfg.train.envs
    fns = [_make_env({**d, **scale.server(i)}, i, cfg.train.seed, 1 if n > 1 or scale.kind == "ray"
                     else cfg.train.torch_threads, subprocess=n > 1 and scale.kind != "ray") for i in range(n)]
    if scale.kind == "ray":
        from genesis_rl.training.ray_vec_env import RayVecEnv

        return RayVecEnv(fns, scale.ray_address, scale.ray_resources(0))
    return SubprocVecEnv(fns, start_method="spawn") if n > 1 else DummyVecEnv(fns)


def check_scale(cfg: RunConfig, scale: ExecutorSettings | None) -> ExecutorSettings:
    """The executor for ``cfg``'s envs, checked before the run folder is touched (Ray installed and its
    address answering; one CARLA server per env)."""
    from genesis_rl.distributed.servers import servers_for_workers

    scale = replace(scale or ExecutorSettings(), workers=cfg.train.envs, what="--envs")
    scale.preflight()
    servers = tuple(s for s in scale.servers if s is not None)
    return replace(scale, servers=tuple(servers_for_workers(cfg.env.backend, servers, cfg.train.envs, "--envs")))


class _Callbacks:
    """Progress bar, per-episode metrics (CSV + TensorBoard) and checkpoints at rollout boundaries."""

    @staticmethod
    def make(run: Path, cfg: RunConfig, start_steps: int, progress: bool,
             episode_sums: dict[int, dict[str, Any]] | None = None):  # noqa: ANN205

        knobs = list(cfg.env.knobs)

        class TrainingCallback(BaseCallback):
            def __init__(self) -> None:
                super().__init__()
                self.bar: Any = None  # a tqdm bar, made in _on_training_start
                # per env, the sums of the episode it is in; a checkpoint keeps them (an episode may span one)
                self.acc: dict[int, dict[str, Any]] = dict(episode_sums or {})
                self.last_ckpt = start_steps
                self.episodes_path = run / "episodes.csv"

            def _on_training_start(self) -> None:
                self.bar = tqdm(total=cfg.train.total_timesteps, initial=start_steps, unit="step",
                                desc="train", disable=not progress, smoothing=0.05)

            def _on_rollout_start(self) -> None:
                # here the previous rollout's update is done and the next has not begun: the only point where
                # a checkpoint holds all the trainer's state (at train.checkpoint_every, rounded up to rollouts)
                if self.model.num_timesteps - self.last_ckpt >= cfg.train.checkpoint_every:
                    self.checkpoint()

            def checkpoint(self) -> None:
                with deferred_signals():  # a signal here is taken once last_ckpt names the checkpoint written
                    save_checkpoint(run, self.model, self.model.num_timesteps, self.acc)
                    self.last_ckpt = self.model.num_timesteps

            def _on_step(self) -> bool:
                n_envs = self.training_env.num_envs
                self.bar.update(n_envs)
                for i, info in enumerate(self.locals["infos"]):
                    a = self.acc.setdefault(i, {"reward": 0.0, "iou": [], "knobs": [], "collisions": 0})
                    if info.get("start_step"):  # the start head's choice: no tick to account for
                        a["start"] = dict(info["start"])
                        continue
                    a["reward"] += float(self.locals["rewards"][i])
                    a["iou"].append(info["iou"])
                    a["knobs"].append([info["knobs"][k] for k in knobs])
                    a["collisions"] += int(info["collision"])
                    if "episode_violations" in info:
                        self._episode_done(a, info["episode_violations"])
                        self.acc.pop(i)
                return True

            def _episode_done(self, a: dict[str, Any], violations: dict[str, float]) -> None:
                knob_mean = np.mean(a["knobs"], axis=0)
                row = {"timesteps": self.num_timesteps, "episode_reward": round(a["reward"], 4),
                       "mean_iou": round(float(np.mean(a["iou"])), 4), "collisions": a["collisions"],
                       **{f"violation_{k}": round(v, 4) for k, v in violations.items()},
                       **{f"mean_{k}": round(float(v), 3) for k, v in zip(knobs, knob_mean, strict=True)},
                       **{f"start_{k}": round(float(v), 3) for k, v in a.get("start", {}).items()}}
                for k, v in row.items():
                    if k != "timesteps":
                        self.logger.record(f"episode/{k}", v)
                new = not self.episodes_path.exists()
                with deferred_signals(), self.episodes_path.open("a", newline="") as fh:  # whole rows only
                    w = csv.DictWriter(fh, fieldnames=list(row))
                    if new:
                        w.writeheader()
                    w.writerow(row)
                self.bar.set_postfix(ep_reward=f"{a['reward']:.0f}", coll=a["collisions"])

            def _on_training_end(self) -> None:
                self.bar.close()

        return TrainingCallback()


def update_threads(cfg: RunConfig) -> int:
    """Torch threads for the learner's updates between rollouts (``RolloutThreads``): ``train.torch_threads``,
    else one for SAC (a gradient step on 128 feature vectors through a small MLP after every env step: a second
    OpenMP thread gains nothing there, and its spinning between steps starves the env processes and any other
    training on the machine; docs/benchmarks.md) and torch's default for PPO (its image minibatches use every
    core)."""
    return cfg.train.torch_threads or (1 if cfg.train.algorithm == "sac" else 0)


def max_timesteps(cfg: RunConfig) -> int:
    """The steps a run of ``cfg`` ends at: SB3 collects whole rollouts (PPO: ppo.n_steps over all envs; SAC:
    sac.train_freq steps of every env), so total_timesteps rounds up."""
    n = cfg.ppo.n_steps if cfg.train.algorithm in PPO_FAMILY else cfg.sac.train_freq * cfg.train.envs
    return -(-cfg.train.total_timesteps // n) * n


def new_model(cfg: RunConfig, env: Any, policy: str) -> BaseAlgorithm:
    """A fresh learner of ``train.algorithm`` for ``env``, seeded with ``train.seed`` (a checkpoint or agent is
    loaded with the same settings: training/safe_load.py)."""
    return learner_class(cfg.train.algorithm)(policy, env, device=cfg.device, verbose=0,
                                              **learner_kwargs(cfg, policy))


def prepare_run(out: Path, cfg: RunConfig, force: bool, resume: bool, argv: list[str],
                total_timesteps: int | None = None, progress: bool = True,
                made: list[Path] | None = None) -> RunConfig:
    """Create (or reopen with ``resume``) the run folder; returns the config the run uses. On resume,
    ``total_timesteps`` may raise the run's target (it is written back to its config.toml). Call it holding
    the folder (``output_folder.claim``). ``made`` gets ``out`` once the folder is (re)made for this run."""
    if resume:
        if not (out / "config.toml").is_file():
            raise UserInputError(f"--resume: '{out}' is not a run folder (no config.toml)")
        # a run continues with the files it began with: an edited config would mix two setups in episodes.csv
        check_run(out, "--resume", "restore it, or train a new run (another --out, or --force to replace this one)",
                  hints={"config.toml": "--resume continues a run with the settings it began with (only --steps "
                                        "may change)"})
        adopt_pins(out)  # a run from before the pins: checked from now on
        if total_timesteps is None:
            return load_run_config(out / "config.toml")
        cfg = load_run_config(out / "config.toml", {"train": {"total_timesteps": total_timesteps}})
        done = read_last(out, 2**63)[0] if (out / CHECKPOINTS / "last.json").is_file() else 0
        if total_timesteps < done:
            raise UserInputError(f"--steps {total_timesteps}: the run in '{out}' has trained {done} steps already; "
                                 f"allowed: --steps >= {done}")
        return cfg  # written back to config.toml once the checkpoint has loaded

    # the catalog is resolved before an old run is removed, so a bad catalog setting loses nothing
    catalog = catalog_or_generate(cfg.env.catalog, cfg.env.map, cfg.env.scenes, cfg.env.catalog_seed,
                                  map_field="env.map", progress=progress)
    commit = git_commit()
    with deferred_signals():  # a folder with all of its set-up files or none (and then removed by train)
        if made is not None:
            made.append(out)
        output_folder.replace(out, "run")
        catalog.save(out / "catalog.json")
        atomic_write_text(out / "config.toml", cfg.to_toml())
        atomic_write_json(out / "run.json", {
            "package": "genesis-rl", "version": __version__, "git_commit": commit,
            "python": sys.version.split()[0], "command": argv, "seed": cfg.train.seed,
            "catalog": {"map": catalog.map, "seed": catalog.seed, "scenes": len(catalog.scenes)},
            "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "pins": current_pins(out, asdict(cfg.env)),  # training/pinning.py: checked whenever the run is reopened
        }, indent=2)
    return cfg


def train(cfg: RunConfig, out: Path, force: bool = False, resume: bool = False, progress: bool = True,
          argv: list[str] | None = None, total_timesteps: int | None = None,
          inputs: Sequence[str | Path | None] = (), scale: ExecutorSettings | None = None,
          callbacks: Sequence[BaseCallback] = ()) -> dict[str, Any]:
    """Train (or ``resume``) the run in ``out``, holding the folder; a new run that fails before its first
    checkpoint is removed. ``inputs`` are files the command reads (its config), which ``out`` may not hold.
    ``scale``: where the envs run (default: subprocesses); not part of the run's config, so a run may resume
    on another executor. ``callbacks``: more SB3 callbacks (``bench train`` times the phases with one)."""
    out = Path(out)
    if not resume:
        scale = check_scale(cfg, scale)
    read = [cfg.env.catalog, cfg.env.odd, cfg.env.rulebook]  # the files the run's env reads
    with output_folder.claim(out, "run", force, resume=resume, inputs=[*read, *inputs]):
        made: list[Path] = []  # the folder, once prepare_run has (re)made it: before that it is the user's
        try:
            cfg = prepare_run(out, cfg, force, resume, argv or [], total_timesteps, progress, made)
            return _train_prepared(cfg, out, resume, progress, check_scale(cfg, scale) if resume else scale,
                                   callbacks)
        except BaseException as err:
            interrupted = isinstance(err, KeyboardInterrupt)
            if not resume and not made:  # stopped before the folder was touched (e.g. making the catalog)
                if interrupted:
                    set_resume_hint(err, f"stopped before '{out}' was written; run the command again")
            elif not resume and not (out / CHECKPOINTS / "last.json").exists():
                # nothing was trained (e.g. the system under test failed to load): leave no folder behind that
                # a corrected re-run would need --force to replace
                with deferred_signals():  # a second signal does not leave half a folder
                    shutil.rmtree(out, ignore_errors=True)
                if interrupted:
                    set_resume_hint(err, f"no checkpoint was written yet, so '{out}' was removed; run the "
                                         "command again")
            elif interrupted and resume_hint(err) is None:
                set_resume_hint(err, f"--resume continues the run in '{out}' from its last checkpoint")
            raise


def _train_prepared(cfg: RunConfig, out: Path, resume: bool, progress: bool,
                    scale: ExecutorSettings | None = None, extra: Sequence[BaseCallback] = ()) -> dict[str, Any]:

    check_device_present(cfg.device_section, cfg.device)
    if cfg.train.torch_threads:
        torch.set_num_threads(cfg.train.torch_threads)
    env = build_vec_env(cfg, out / "catalog.json", scale)
    try:
        policy = policy_name(cfg.train.algorithm, sb3_policy(cfg.env.observation_mode))
        sums: dict[int, dict[str, Any]] = {}
        if resume:
            resumed = load_checkpoint(out, env, cfg.device, max_timesteps(cfg), cfg)
            model, done, sums = resumed.model, resumed.steps, resumed.episode_sums
            if load_run_config(out / "config.toml") != cfg:  # --steps raised the target
                atomic_write_text(out / "config.toml", cfg.to_toml())
                write_pins(out, asdict(cfg.env))  # genesis-rl changed it: re-pinned
        else:
            model = new_model(cfg, env, policy)
            done = 0
        formats = ["csv"]
        try:
            import tensorboard  # noqa: F401

            formats.append("tensorboard")
        except ImportError:
            pass
        model.set_logger(configure(str(out / "tb"), formats))
        remaining = cfg.train.total_timesteps - done
        t0 = time.perf_counter()
        if remaining > 0:
            cb = _Callbacks.make(out, cfg, done, progress, sums)
            # envs in other processes: this one needs a single thread while they step (training/throughput.py)
            remote_envs = cfg.train.envs > 1 or (scale is not None and scale.kind == "ray")
            threads = [RolloutThreads(update_threads(cfg))] if remote_envs else []
            try:
                model.learn(total_timesteps=remaining, callback=[cb, *threads, *extra], reset_num_timesteps=not resume,
                            progress_bar=False)
            except KeyboardInterrupt as err:
                # a checkpoint is only whole between rollouts, so none is taken here: --resume goes back to the
                # last one and trains the steps since again, exactly as before
                if (out / CHECKPOINTS / "last.json").exists():
                    set_resume_hint(err, f"stopped at step {model.num_timesteps}; --resume continues from the "
                                         f"checkpoint at step {cb.last_ckpt}")
                raise
            except RayWorkersLost as err:  # a lost Ray env or node: stop at the last whole checkpoint (exit 3)
                if (out / CHECKPOINTS / "last.json").exists():
                    raise RayWorkersLost(f"{err} at step {model.num_timesteps}; the run stops at its checkpoint at "
                                         f"step {cb.last_ckpt}: continue with genesis-rl train --resume --out {out}"
                                         ) from None
                raise RayWorkersLost(f"{err} at step {model.num_timesteps}, before the run's first checkpoint; "
                                     "nothing is kept: run the command again") from None
            cb.checkpoint()
        atomic_write(out / "agent.zip", lambda q: model.save(q))
        seconds = time.perf_counter() - t0
        result = {"run": str(out), "timesteps": int(model.num_timesteps), "trained_steps_now": max(remaining, 0),
                  "seconds": round(seconds, 1),
                  "steps_per_second": round(max(remaining, 0) / seconds, 2) if seconds > 0 else None}
        atomic_write_json(out / "train_result.json", result, indent=2)
        return result
    except KeyboardInterrupt:
        _close_after_interrupt(env)
        raise
    finally:
        env.close()


def _close_after_interrupt(env: Any) -> None:
    """Close env processes that an interrupt may have caught mid-step: SB3's ``close`` waits for every env's
    answer to that step, which can block for ever when some had been read already, and fails (EOFError) when a
    worker was ended by the same signal (SIGTERM to the whole process group). The workers are told to close,
    given 10 s, then terminated."""
    if not isinstance(env, SubprocVecEnv) or env.closed:
        return
    with deferred_signals():
        for remote in env.remotes:
            try:
                remote.send(("close", None))
            except OSError:  # that worker is gone already
                pass
        for process in env.processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
        for remote in env.remotes:
            remote.close()
        env.closed = True
