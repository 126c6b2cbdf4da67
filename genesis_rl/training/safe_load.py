"""Load SB3 agents, checkpoints and replay buffers without unpickling anything a file holds.

SB3 keeps a model as a zip: tensors in ``*.pth`` files (which SB3 reads with ``torch.load(weights_only=True)``,
safe) and everything else in the JSON ``data``, where what JSON cannot hold (the policy class, the
spaces, the schedules, the last observation, the episode-info deque) is a cloudpickle under a
``:serialized:`` key: ``SB3.load`` unpickles those, and so runs any code a crafted file puts there.

Here nothing of ``data`` is unpickled: the zip is read, a fresh ``data`` is written into an in-memory copy
from the run's checked config (the learner's settings, exactly as ``train`` builds them), the spaces the
config's env has, and from the file only its counters (checked integers and floats); every
``:serialized:`` entry is replaced through SB3's ``custom_objects`` so SB3 never calls cloudpickle, and only
the ``.pth`` files the learner has are copied. What a resumed run needs beyond that (the last observation
and episode starts, the episode-info deque) is in ``step_N.sb3.npz`` beside the checkpoint, and SAC's
replay buffer in ``step_N.replay.npz``: plain arrays, read with ``allow_pickle=False``.

An agent or checkpoint of an older genesis-rl that only loads through pickle (no run config beside it, a
checkpoint without its ``.sb3.npz``, a ``.replay.pkl`` buffer) is refused unless the command is given
``--trust-pickle`` (genesis_rl/core/trust.py).
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.bounded_zip import read_members
from genesis_rl.core.trust import pickle_trusted

if TYPE_CHECKING:
    from gymnasium import spaces

    from genesis_rl.training.config import RunConfig

#: The largest ``data`` entry read from an agent's zip (SB3's is a few kB; a pickled observation a few MB).
MAX_DATA_BYTES = 256 * 1024 * 1024
#: Counters taken from the file, with the range each may take.
_COUNTERS: dict[str, tuple[type, float, float]] = {
    "num_timesteps": (int, 0, 2**62), "_total_timesteps": (int, 0, 2**62), "_num_timesteps_at_start": (int, 0, 2**62),
    "_episode_num": (int, 0, 2**62), "_n_updates": (int, 0, 2**62), "_current_progress_remaining": (float, 0.0, 1.0),
    "start_time": (float, 0, 2**63 - 1), "_stats_window_size": (int, 1, 100_000),  # start_time: ns, or 0.0
}
#: The tensors files each learner's zip holds (policy and optimizers) besides pytorch_variables.pth.
_STATE_DICTS = {"ppo": {"policy", "policy.optimizer"}, "recurrent_ppo": {"policy", "policy.optimizer"},
                "sac": {"policy", "actor.optimizer", "critic.optimizer", "ent_coef_optimizer"}}
_VARIABLES: dict[str, set[str]] = {"ppo": set(), "recurrent_ppo": set(), "sac": {"log_ent_coef", "ent_coef_tensor"}}
TRUST_HINT = ("pass --trust-pickle to load it the old way if you trust whoever made the file (unpickling runs any "
              "code it holds)")


#: Classes a stored ``policy_kwargs`` may name (SB3 writes a readable ``<class '...'>`` beside each pickle):
#: matched by their full name, never imported from the file.
_KWARG_CLASSES = {
    "features_extractor_class": ("stable_baselines3.common.torch_layers.NatureCNN",
                                 "stable_baselines3.common.torch_layers.FlattenExtractor",
                                 "stable_baselines3.common.torch_layers.CombinedExtractor",
                                 "genesis_rl.training.throughput.ChannelsLastNatureCNN"),
    "activation_fn": tuple(f"torch.nn.modules.activation.{n}" for n in ("Tanh", "ReLU", "ELU", "LeakyReLU", "GELU",
                                                                         "SiLU")),
    "optimizer_class": ("torch.optim.adam.Adam", "torch.optim.adamw.AdamW", "torch.optim.rmsprop.RMSprop"),
}
_KWARG_SCALARS = {"log_std_init": float, "use_sde": bool, "ortho_init": bool, "normalize_images": bool,
                  "share_features_extractor": bool, "squash_output": bool, "full_std": bool, "use_expln": bool,
                  "n_critics": int, "clip_mean": float, "lstm_hidden_size": int, "n_lstm_layers": int,
                  "shared_lstm": bool, "enable_critic_lstm": bool}
#: integer settings a file may not set beyond what genesis-rl builds (a claimed 10**9 LSTM units is an allocation,
#: not a model); the LSTM's are the [recurrent] table's ranges (training/config.py)
_KWARG_INT_BOUNDS = {"n_critics": (1, 16)}


def _class_named(text: Any, allowed: tuple[str, ...]) -> type | None:
    import importlib
    import re

    match = re.fullmatch(r"<class '([\w.]+)'>", text) if isinstance(text, str) else None
    if match is None or match.group(1) not in allowed:
        return None
    module, _, name = match.group(1).rpartition(".")
    return getattr(importlib.import_module(module), name, None)  # a fixed list of the package's and SB3's own


def stored_policy_kwargs(data: dict[str, Any], path: Path, what: str) -> dict[str, Any] | None:
    """The ``policy_kwargs`` the model in ``data`` was built with, read from their JSON (the readable copy SB3
    writes beside the pickle) and an allow-list of classes and scalar settings; None when the file has none."""
    stored = data.get("policy_kwargs")
    if stored is None or isinstance(stored, dict) and ":serialized:" in stored and \
            not set(stored) - {":type:", ":serialized:"}:
        return None  # none, or a pickle with no readable copy: the config's
    if not isinstance(stored, dict):
        raise UserInputError(f"{what}: '{path}': data['policy_kwargs'] is not a table")
    out: dict[str, Any] = {}

    def refuse(key: str) -> UserInputError:
        return UserInputError(f"{what}: '{path}': policy_kwargs['{key}'] = {str(stored[key])[:80]!r} is not one "
                              f"genesis-rl rebuilds without unpickling; {TRUST_HINT}")

    from genesis_rl.training.config import RECURRENT_RANGES

    bounds = {**_KWARG_INT_BOUNDS, **{k: (r.low, r.high) for k, r in RECURRENT_RANGES.items()}}

    def numbers(value: Any) -> bool:
        return isinstance(value, list) and all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 4096
                                               for v in value)

    for key, value in stored.items():
        if key in (":type:", ":serialized:"):
            continue
        if key in _KWARG_CLASSES:
            cls = _class_named(value, _KWARG_CLASSES[key])
            if cls is None:
                raise refuse(key)
            out[key] = cls
        elif key in _KWARG_SCALARS:
            kind = _KWARG_SCALARS[key]
            ok = isinstance(value, bool) if kind is bool else (
                isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value))
            low, high = bounds.get(key, (-math.inf, math.inf))
            if not ok or kind is int and not (isinstance(value, int) and low <= value <= high):
                raise refuse(key)
            out[key] = kind(value)
        elif key == "net_arch":
            if numbers(value):
                out[key] = list(value)
            elif isinstance(value, dict) and set(value) <= {"pi", "vf", "qf"} and all(map(numbers, value.values())):
                out[key] = {k: list(v) for k, v in value.items()}
            else:
                raise refuse(key)
        elif key in ("optimizer_kwargs", "features_extractor_kwargs"):
            if not isinstance(value, dict) or not all(
                    isinstance(k, str) and (isinstance(v, (bool, int)) or isinstance(v, float) and math.isfinite(v))
                    for k, v in value.items()):
                raise refuse(key)
            out[key] = dict(value)
        else:
            raise refuse(key)
    return out


def learner_class(algorithm: str) -> Any:
    """The SB3 class of ``train.algorithm`` (sb3-contrib's RecurrentPPO for ``recurrent_ppo``)."""
    if algorithm == "recurrent_ppo":
        from sb3_contrib import RecurrentPPO

        return RecurrentPPO
    from stable_baselines3 import PPO, SAC

    return SAC if algorithm == "sac" else PPO


def policy_name(algorithm: str, policy: str) -> str:
    """The learner's name for the observation's policy class: the recurrent learner's are the LSTM twins of
    SB3's (``MlpPolicy`` -> ``MlpLstmPolicy``)."""
    return policy.replace("Policy", "LstmPolicy") if algorithm == "recurrent_ppo" else policy


def learner_kwargs(cfg: RunConfig, policy: str) -> dict[str, Any]:
    """The SB3 constructor settings of ``cfg``'s learner (``train.algorithm``): a new model and a loaded one
    are built from the same."""
    from genesis_rl.training.throughput import policy_kwargs

    kwargs = policy_kwargs(policy)
    if cfg.train.algorithm == "sac":
        s = cfg.sac
        return {"learning_rate": s.learning_rate, "buffer_size": s.buffer_size, "learning_starts": s.learning_starts,
                "batch_size": s.batch_size, "tau": s.tau, "gamma": s.gamma, "train_freq": s.train_freq,
                "gradient_steps": s.gradient_steps, "ent_coef": s.sb3_ent_coef(), "seed": cfg.train.seed,
                "policy_kwargs": {**kwargs, "net_arch": list(s.net_arch)}}
    p = cfg.ppo
    if cfg.train.algorithm == "recurrent_ppo":
        r = cfg.recurrent
        kwargs = {**kwargs, "lstm_hidden_size": r.lstm_hidden_size, "n_lstm_layers": r.n_lstm_layers,
                  "enable_critic_lstm": r.enable_critic_lstm}
    return {"learning_rate": p.learning_rate, "n_steps": p.n_steps // cfg.train.envs,
            "batch_size": min(p.batch_size, p.n_steps), "n_epochs": p.n_epochs, "gamma": p.gamma,
            "gae_lambda": p.gae_lambda, "clip_range": p.clip_range, "ent_coef": p.ent_coef, "vf_coef": p.vf_coef,
            "max_grad_norm": p.max_grad_norm, "seed": cfg.train.seed,
            "policy_kwargs": {**kwargs, "log_std_init": p.log_std_init}}


def model_spaces(cfg: RunConfig) -> tuple[spaces.Space, spaces.Box]:
    """The observation and action spaces a model of ``cfg`` has, as SB3 sees them (images channels first,
    as its VecTransposeImage wrapper gives them)."""
    from gymnasium import spaces
    from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
    from stable_baselines3.common.vec_env import VecTransposeImage

    from genesis_rl.env.observation import actor_feature_names, observation_space
    from genesis_rl.world.knobs import KnobActionMapper

    c = cfg.env
    obs = observation_space(c.observation_mode, c.obs_height, c.obs_width, len(c.knobs), c.obs_history,
                            actor_feature_names(c.knobs), c.start_head)
    action = spaces.Box(-1.0, 1.0, (KnobActionMapper(c.knobs, c.max_step_fraction, c.disabled_knobs).action_dim,),
                        np.float32)

    def channels_last(s: spaces.Space) -> bool:
        return bool(is_image_space(s) and not is_image_space_channels_first(s))  # type: ignore[arg-type]

    if isinstance(obs, spaces.Dict):
        if any(channels_last(s) for s in obs.spaces.values()):
            obs = spaces.Dict({k: VecTransposeImage.transpose_space(s, k) if is_image_space(s) else s  # type: ignore[arg-type]
                               for k, s in obs.spaces.items()})
    elif channels_last(obs):
        obs = VecTransposeImage.transpose_space(obs)  # type: ignore[arg-type]
    return obs, action


def _read_zip(path: Path, what: str) -> tuple[dict[str, Any], dict[str, bytes]]:
    """The zip's ``data`` (parsed JSON) and its ``.pth`` members (bytes)."""
    try:
        with zipfile.ZipFile(path) as archive:
            infos = {i.filename: i for i in archive.infolist()}
            if "data" not in infos:
                raise UserInputError(f"{what}: '{path}' is not an SB3 agent (no 'data' in the zip)")
            if infos["data"].file_size > MAX_DATA_BYTES:
                raise UserInputError(f"{what}: '{path}': its 'data' is {infos['data'].file_size} bytes; allowed: "
                                     f"up to {MAX_DATA_BYTES}")
            data = json.loads(read_members(archive, ["data"], f"{what}: '{path}'")["data"].decode("utf-8"))
            pth = read_members(archive, [name for name in infos if name.endswith(".pth")], f"{what}: '{path}'")
    except UserInputError:
        raise
    except (OSError, zipfile.BadZipFile, UnicodeDecodeError, ValueError, RecursionError) as err:
        raise UserInputError(f"{what}: '{path}' cannot be loaded as an SB3 agent: {err}") from None
    if not isinstance(data, dict):
        raise UserInputError(f"{what}: '{path}': its 'data' is not a JSON object")
    return data, pth


def _counter(data: dict[str, Any], key: str, path: Path, what: str) -> Any:
    kind, lo, hi = _COUNTERS[key]
    value = data[key]
    ok = (isinstance(value, int) and not isinstance(value, bool)) if kind is int else (
        isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value))
    if not ok or not lo <= value <= hi:
        raise UserInputError(f"{what}: '{path}': data['{key}'] = {str(value)[:40]!r}; allowed: "
                             f"{'an integer' if kind is int else 'a number'} in {lo}..{hi}")
    return value


def _variables(blob: bytes, algorithm: str, path: Path, what: str) -> None:
    """``pytorch_variables.pth`` may name only the learner's own variables (SB3 sets each by its name)."""
    import torch

    try:
        variables = torch.load(io.BytesIO(blob), map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - the safe unpickler refuses with many kinds
        raise UserInputError(f"{what}: '{path}': pytorch_variables.pth cannot be read: {err}") from None
    names = set(variables) if isinstance(variables, dict) else {"?"}
    if not names <= _VARIABLES[algorithm]:
        raise UserInputError(f"{what}: '{path}': pytorch_variables.pth names {sorted(map(str, names))}; a "
                             f"{algorithm.upper()} agent has at most {sorted(_VARIABLES[algorithm])}")


def load_model(path: Path, cfg: RunConfig | None, *, env: Any = None, device: str = "cpu",
               resume_state: dict[str, Any] | None = None, force_reset: bool = True, what: str = "--agent",
               trust_pickle: bool | None = None) -> Any:
    """The SB3 model in ``path`` (PPO, SAC or RecurrentPPO, as ``cfg`` says), built from ``cfg`` and the file's
    tensors.

    ``resume_state``: what :func:`read_sb3_state` read beside a checkpoint (the last observation and episode
    starts), for a resumed run; None for an agent that only acts. ``trust_pickle`` (None: the command's
    ``--trust-pickle``) loads through SB3's own ``load`` instead: what an older file without its run's
    config needs."""
    path = Path(path)
    trust = pickle_trusted() if trust_pickle is None else trust_pickle
    if cfg is None:
        learners = {name: learner_class(name) for name in ("ppo", "sac", "recurrent_ppo")}
        if not trust:
            raise UserInputError(f"{what}: '{path}' has no run config.toml beside it (in its folder or the one "
                                 "above checkpoints/), and an agent is rebuilt from its run's config, never "
                                 f"unpickled from the file; pass its run folder, or {TRUST_HINT}")
        errors = []
        for name, cls in learners.items():
            try:
                return cls.load(path, env=env, device=device, force_reset=force_reset)
            except Exception as err:  # noqa: BLE001 - a corrupt zip raises many kinds
                errors.append(f"as {name.upper()}: {err}")
        raise UserInputError(f"{what}: '{path}' cannot be loaded ({'; '.join(errors)})")
    algorithm = cfg.train.algorithm
    cls = learner_class(algorithm)
    if trust:
        try:
            model = cls.load(path, env=env, device=device, force_reset=force_reset)
        except Exception as err:  # noqa: BLE001 - a corrupt zip raises many kinds
            raise UserInputError(f"{what}: '{path}' cannot be loaded: {err}") from None
        if resume_state is not None:  # SB3's own load keeps no LSTM memory either
            restore_lstm_states(model, resume_state.get("lstm"))
        return model
    from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit

    from genesis_rl.env.observation import sb3_policy

    data, pth = _read_zip(path, what)
    policy = policy_name(algorithm, sb3_policy(cfg.env.observation_mode))
    settings = learner_kwargs(cfg, policy)
    obs_space, action_space = model_spaces(cfg)
    built = settings.pop("policy_kwargs")
    stored = stored_policy_kwargs(data, path, what)  # what the weights were made with (an older version's)
    custom: dict[str, Any] = {
        "policy_class": cls.policy_aliases[policy], "observation_space": obs_space, "action_space": action_space,
        "policy_kwargs": stored if stored is not None else {**built, **({"use_sde": False} if algorithm == "sac"
                                                                        else {})},
        "lr_schedule": None,  # SB3 remakes it from learning_rate
        "_last_obs": None, "_last_original_obs": None, "_last_episode_starts": None,
        "ep_info_buffer": None, "ep_success_buffer": None,
    }
    clean: dict[str, Any] = {**settings, "verbose": 0, "tensorboard_log": None, "action_noise": None,
                             "n_envs": env.num_envs if env is not None else 1, "use_sde": False,
                             "sde_sample_freq": -1}
    if algorithm == "sac":
        clean.update(replay_buffer_class=None, replay_buffer_kwargs={}, optimize_memory_usage=False, n_steps=1,
                     use_sde_at_warmup=False, target_update_interval=1,
                     target_entropy=float(-np.prod(action_space.shape).astype(np.float32)))
        custom["train_freq"] = TrainFreq(settings["train_freq"], TrainFrequencyUnit.STEP)
    else:
        clean.update(rollout_buffer_class=None, rollout_buffer_kwargs={}, clip_range_vf=None,
                     normalize_advantage=True, target_kl=None)
    for key in _COUNTERS:
        if key in data:
            clean[key] = _counter(data, key, path, what)
    window = int(clean.get("_stats_window_size", 100))
    ep_info: deque = deque(maxlen=window)
    if resume_state is not None:
        custom.update(_last_obs=resume_state["last_obs"], _last_original_obs=resume_state["last_original_obs"],
                      _last_episode_starts=resume_state["last_episode_starts"])
        ep_info.extend(resume_state["ep_info_buffer"][-window:])
    custom["ep_info_buffer"] = ep_info
    custom["ep_success_buffer"] = deque(maxlen=window)
    clean.update({k: None for k in custom})  # placeholders: custom_objects fills each, nothing is unpickled
    members: dict[str, bytes] = {}
    for name, blob in pth.items():
        stem = name[:-len(".pth")]
        if stem in _STATE_DICTS[algorithm]:
            members[name] = blob
        elif stem == "pytorch_variables":
            _variables(blob, algorithm, path, what)
            members[name] = blob
        else:
            raise UserInputError(f"{what}: '{path}' holds '{name}', which a {algorithm.upper()} agent does not "
                                 f"have (its run's config.toml says train.algorithm = \"{algorithm}\")")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as out:
        out.writestr("data", json.dumps(clean))
        for name, blob in members.items():
            out.writestr(name, blob)
    buffer.seek(0)
    try:
        model = cls.load(buffer, env=env, device=device, custom_objects=custom, force_reset=force_reset)
    except Exception as err:  # noqa: BLE001 - weights of another shape, a missing tensor file, ...
        raise UserInputError(f"{what}: '{path}' does not fit the model its run's config.toml describes "
                             f"({type(err).__name__}: {str(err)[:300]})") from None
    if resume_state is not None:
        restore_lstm_states(model, resume_state.get("lstm"))
    return model


# -- what a resumed run needs beyond the zip ------------------------------------------------------------
def sb3_state_path(checkpoint_zip: Path) -> Path:
    """``step_N.sb3.npz`` beside ``step_N.zip``."""
    return checkpoint_zip.with_name(checkpoint_zip.name.removesuffix(".zip") + ".sb3.npz")


def _put(arrays: dict[str, np.ndarray], name: str, value: Any) -> None:
    if value is None:
        return
    if isinstance(value, dict):
        for k, v in value.items():
            arrays[f"{name}/{k}"] = np.asarray(v)
    else:
        arrays[name] = np.asarray(value)


def _take(z: Any, name: str) -> Any:
    if name in z.files:
        return z[name]
    keys = [f for f in z.files if f.startswith(name + "/")]
    return {f.split("/", 1)[1]: z[f] for f in keys} if keys else None


#: bytes any member of an ``.npz`` may take whatever the run's arrays: positions and the episode-info JSON are
#: a few KB; a run's own arrays may be larger, and then its largest one is the ceiling
NPZ_MEMBER_FLOOR = 16 * 2**20


def check_npz_headers(path: Path, ceiling: int, damaged: Any) -> None:
    """Refuse an ``.npz`` member whose header claims more than ``ceiling`` bytes, before numpy allocates the
    claimed shape (a header of 10**12 elements is a MemoryError, or the machine swapping, not a refusal)."""
    fmt = np.lib.format
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):
                continue
            member = info.filename.removesuffix(".npy")
            with zf.open(info) as fh:
                version = fmt.read_magic(fh)
                if version == (1, 0):
                    shape, _, dtype = fmt.read_array_header_1_0(fh)
                elif version == (2, 0):
                    shape, _, dtype = fmt.read_array_header_2_0(fh)
                else:  # numpy writes 3.0 only for non-Latin-1 field names, which these files never hold
                    raise damaged(f"member '{member}' has .npy format version {version[0]}.{version[1]}")
            size = math.prod(shape) * dtype.itemsize
            if size > ceiling:
                raise damaged(f"member '{member}' claims shape {list(shape)} of {dtype}, {size:,} bytes; the run's "
                              f"arrays take at most {ceiling:,}")


def write_sb3_state(path: Path, model: Any) -> None:
    """The last observation, episode starts and episode-info deque of ``model``, as plain arrays."""
    arrays: dict[str, np.ndarray] = {}
    _put(arrays, "last_obs", model._last_obs)
    _put(arrays, "last_original_obs", getattr(model, "_last_original_obs", None))
    _put(arrays, "last_episode_starts", model._last_episode_starts)
    lstm = getattr(model, "_last_lstm_states", None)  # RecurrentPPO: the memory of each env's episode so far
    if lstm is not None:
        for part, pair in zip(("pi", "vf"), lstm, strict=True):
            for name, tensor in zip(("h", "c"), pair, strict=True):
                arrays[f"lstm/{part}_{name}"] = tensor.detach().cpu().numpy()
    infos = [{k: int(v) if isinstance(v, (int, np.integer)) else float(v) for k, v in info.items()
              if isinstance(v, (int, float, np.floating, np.integer))} for info in (model.ep_info_buffer or [])]
    arrays["ep_info_buffer_json"] = np.asarray(json.dumps(infos))
    with Path(path).open("wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]


def read_sb3_state(path: Path, cfg: RunConfig, n_envs: int) -> dict[str, Any]:
    """What :func:`write_sb3_state` wrote, each array checked against the spaces of ``cfg``'s env."""
    from gymnasium import spaces

    obs_space, _ = model_spaces(cfg)

    def damaged(why: str) -> UserInputError:
        return UserInputError(f"--resume: checkpoint file '{path}' is damaged ({why}); start the run again with "
                              "--force")

    def checked_obs(value: Any, name: str, optional: bool) -> Any:
        if value is None:
            if optional:
                return None
            raise damaged(f"no '{name}'")
        parts = value if isinstance(obs_space, spaces.Dict) else {"": value}
        want = obs_space.spaces if isinstance(obs_space, spaces.Dict) else {"": obs_space}
        if not isinstance(parts, dict) or set(parts) != set(want):
            raise damaged(f"'{name}' has parts {sorted(parts) if isinstance(parts, dict) else '?'}")
        for k, space in want.items():
            arr = parts[k]
            shape = (n_envs, *(space.shape or ()))
            if not isinstance(arr, np.ndarray) or arr.shape != shape or arr.dtype != space.dtype:
                raise damaged(f"'{name}' {k} is not {space.dtype}{list(shape)}")
        return value

    obs_parts = obs_space.spaces.values() if isinstance(obs_space, spaces.Dict) else [obs_space]
    ceiling = max([NPZ_MEMBER_FLOOR, *(n_envs * math.prod(sp.shape or ()) * np.dtype(sp.dtype).itemsize
                                       for sp in obs_parts)])
    try:
        check_npz_headers(path, ceiling, damaged)
        with np.load(path, allow_pickle=False) as z:
            last_obs = checked_obs(_take(z, "last_obs"), "last_obs", False)
            original = checked_obs(_take(z, "last_original_obs"), "last_original_obs", True)
            starts = _take(z, "last_episode_starts")
            if not isinstance(starts, np.ndarray) or starts.shape != (n_envs,) or starts.dtype != np.bool_:
                raise damaged(f"'last_episode_starts' is not {n_envs} booleans")
            infos = json.loads(str(z["ep_info_buffer_json"]))
            lstm = _take(z, "lstm")
            if cfg.train.algorithm == "recurrent_ppo":
                shape = (cfg.recurrent.n_lstm_layers, n_envs, cfg.recurrent.lstm_hidden_size)
                parts = ("pi_h", "pi_c", "vf_h", "vf_c")
                if not isinstance(lstm, dict) or set(lstm) != set(parts) or any(
                        lstm[k].shape != shape or lstm[k].dtype != np.float32 for k in parts):
                    raise damaged(f"'lstm' is not the recurrent policy's four float32{list(shape)} states")
            elif lstm is not None:
                raise damaged(f"it holds an LSTM's states, which a {cfg.train.algorithm} run does not have")
    except UserInputError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, RecursionError) as err:  # EOFError: empty
        raise damaged(f"{type(err).__name__}: {err}") from None
    except MemoryError:  # the headers are checked; this is the safety net should memory be short anyway
        raise damaged("it does not fit in memory") from None
    if not isinstance(infos, list) or not all(isinstance(i, dict) and all(
            isinstance(v, (int, float)) for v in i.values()) for i in infos):
        raise damaged("'ep_info_buffer_json' is not a list of numbers by name")
    return {"last_obs": last_obs, "last_original_obs": original, "last_episode_starts": starts,
            "ep_info_buffer": infos, "lstm": lstm}


def restore_lstm_states(model: Any, lstm: dict[str, np.ndarray] | None) -> None:
    """Give a resumed RecurrentPPO the memory its envs' episodes had at the checkpoint (sb3-contrib leaves
    it out of the zip and starts from zeros, so the rollout after a resume would differ)."""
    if lstm is None:
        return
    import torch
    from sb3_contrib.common.recurrent.type_aliases import RNNStates

    def tensor(key: str) -> torch.Tensor:
        return torch.as_tensor(lstm[key], device=model.device)

    model._last_lstm_states = RNNStates((tensor("pi_h"), tensor("pi_c")), (tensor("vf_h"), tensor("vf_c")))


# -- SAC's replay buffer ----------------------------------------------------------------------------------
_BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def write_replay_buffer(path: Path, buffer: Any) -> None:
    """An SB3 (Dict)ReplayBuffer's arrays and position, as an ``.npz`` (no pickle)."""
    arrays: dict[str, np.ndarray] = {}
    for name in _BUFFER_ARRAYS:
        _put(arrays, name, getattr(buffer, name, None))
    arrays["pos"] = np.asarray(int(buffer.pos), np.int64)
    arrays["full"] = np.asarray(bool(buffer.full))
    with Path(path).open("wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]


def read_replay_buffer(path: Path, buffer: Any) -> None:
    """Fill ``buffer`` (the one the model made from its config) from :func:`write_replay_buffer`'s file;
    every array must have the buffer's own shape and dtype."""

    def damaged(why: str) -> UserInputError:
        return UserInputError(f"--resume: replay buffer '{path}' is damaged ({why}); start the run again with --force")

    own = [getattr(buffer, name, None) for name in _BUFFER_ARRAYS]
    arrays = [a for x in own for a in (x.values() if isinstance(x, dict) else [x]) if isinstance(a, np.ndarray)]
    ceiling = max([NPZ_MEMBER_FLOOR, *(a.nbytes for a in arrays)])  # no member is larger than the buffer's own
    try:
        check_npz_headers(path, ceiling, damaged)
        with np.load(path, allow_pickle=False) as z:
            loaded: dict[str, Any] = {}
            for name in _BUFFER_ARRAYS:
                mine = getattr(buffer, name, None)
                theirs = _take(z, name)
                if mine is None and theirs is None:
                    continue
                mine_parts = mine if isinstance(mine, dict) else {"": mine}
                theirs_parts = theirs if isinstance(theirs, dict) else {"": theirs}
                if theirs is None or set(mine_parts) != set(theirs_parts):
                    raise damaged(f"'{name}' is missing or has other parts")
                for k, arr in mine_parts.items():
                    got = theirs_parts[k]
                    if not isinstance(arr, np.ndarray) or not isinstance(got, np.ndarray) or \
                            got.shape != arr.shape or got.dtype != arr.dtype:
                        raise damaged(f"'{name}' {k} is not what the run's config makes "
                                      f"({getattr(arr, 'dtype', None)}{list(getattr(arr, 'shape', ()))})")
                loaded[name] = theirs
            pos, full = z["pos"], z["full"]
            if pos.shape != () or full.shape != () or full.dtype != np.bool_ or not 0 <= int(pos) < buffer.buffer_size:
                raise damaged(f"pos = {pos!r} and full = {full!r}; allowed: 0..{buffer.buffer_size - 1} and a bool")
    except UserInputError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as err:  # EOFError: an empty file
        raise damaged(f"{type(err).__name__}: {err}") from None
    except MemoryError:  # the headers are checked; this is the safety net should memory be short anyway
        raise damaged("it does not fit in memory") from None
    for name, value in loaded.items():
        if isinstance(value, dict):
            getattr(buffer, name).update({k: np.array(v) for k, v in value.items()})
        else:
            setattr(buffer, name, np.array(value))
    buffer.pos, buffer.full = int(pos), bool(full)
