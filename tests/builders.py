"""Shared builders for the tests: the tiny training run every end-to-end test trains, in one place.

A tiny run trains PPO for a few dozen steps of 64x48 frames with the ``blind`` system: the plumbing under
test (checkpoints, pins, resume, interrupts, the output rule) runs whole in seconds; the agent learns nothing.
"""

from __future__ import annotations

from typing import Any

#: the tiny run's tables; a test overrides a key by passing it, or drops it by passing None
TINY_ENV: dict[str, Any] = {"map": "urban", "scenes": 3, "system": "blind", "episode_steps": 10, "camera_width": 64,
                            "camera_height": 48, "obs_width": 36, "obs_height": 36}
TINY_PPO: dict[str, Any] = {"n_steps": 16, "batch_size": 8, "n_epochs": 2}
TINY_TRAIN: dict[str, Any] = {"total_timesteps": 64, "checkpoint_every": 16, "seed": 3, "torch_threads": 1}


def _value(v: Any) -> str:
    return f'"{v}"' if isinstance(v, str) else str(v).lower() if isinstance(v, bool) else str(v)


def _table(name: str, base: dict[str, Any], over: dict[str, Any] | None) -> str:
    merged = {**base, **(over or {})}
    return f"[{name}]\n" + "".join(f"{k} = {_value(v)}\n" for k, v in merged.items() if v is not None)


def tiny_run(env: dict[str, Any] | None = None, ppo: dict[str, Any] | None = None,
             train: dict[str, Any] | None = None, **tables: dict[str, Any]) -> str:
    """The tiny run's config.toml text; ``tables`` adds tables of its own (``sac={...}``)."""
    parts = [_table("env", TINY_ENV, env), _table("ppo", TINY_PPO, ppo), _table("train", TINY_TRAIN, train)]
    parts += [_table(name, {}, values) for name, values in tables.items()]
    return "\n".join(parts)
