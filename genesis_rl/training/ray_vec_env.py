"""``RayVecEnv``: Stable-Baselines3's vectorised env with each sub-env in a Ray actor, so ``train --envs N
--executor ray`` spreads the environments (and their simulators) over a Ray cluster while SB3 stays the
trainer in this process.

It follows ``SubprocVecEnv`` step for step (auto-reset on done with the terminal observation in ``info``,
seeds and options handed to the next reset), so the same seeds give the same rollouts and the same agent.

An env actor lost mid-run (its worker killed, its node gone) stops the run with :class:`RayWorkersLost`
naming the env and its node; ``train`` turns it into one line naming ``train --resume`` (its last checkpoint
is whole). A replacement env cannot continue the lost one's episode exactly (its simulator state and random
stream went with it, and SB3's rollout holds half an episode), so none is made. A lost head is noticed by
asking it while the driver waits (``distributed/ray_head.py``) and stops the run the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn
from stable_baselines3.common.vec_env.subproc_vec_env import _stack_obs

from genesis_rl.distributed.ray_cluster import (
    RayWorkersLost,
    add_driver_paths,
    driver_paths,
    lost_errors,
    node_address,
    node_alive,
    ray_session,
    where_am_i,
)
from genesis_rl.distributed.ray_head import HeadWatch


class EnvActor:
    """One sub-env in a Ray actor."""

    def __init__(self, env_fn: Callable[[], gym.Env], paths: list[str]) -> None:
        add_driver_paths(paths)
        self.env = env_fn()

    def where(self) -> tuple[str, str]:
        return where_am_i()

    def step(self, action: Any) -> tuple[Any, Any, bool, dict[str, Any], dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        done = terminated or truncated
        info["TimeLimit.truncated"] = truncated and not terminated
        reset_info: dict[str, Any] = {}
        if done:
            info["terminal_observation"] = obs
            obs, reset_info = self.env.reset()
        return obs, reward, done, info, reset_info

    def reset(self, seed: int | None, options: dict[str, Any] | None) -> tuple[Any, dict[str, Any]]:
        return self.env.reset(seed=seed, **({"options": options} if options else {}))

    def get_attr(self, name: str) -> Any:
        return self.env.get_wrapper_attr(name)

    def set_attr(self, name: str, value: Any) -> None:
        setattr(self.env, name, value)

    def env_method(self, name: str, args: Sequence[Any], kwargs: dict[str, Any]) -> Any:
        return self.env.get_wrapper_attr(name)(*args, **kwargs)

    def is_wrapped(self, wrapper_class: type[gym.Wrapper]) -> bool:
        from stable_baselines3.common.env_util import is_wrapped

        return is_wrapped(self.env, wrapper_class)

    def spaces(self) -> tuple[gym.Space, gym.Space]:
        return self.env.observation_space, self.env.action_space

    def close(self) -> None:
        self.env.close()


class RayVecEnv(VecEnv):
    """Sub-envs as Ray actors (one CPU each) on a local Ray (``address`` None) or a cluster."""

    def __init__(self, env_fns: list[Callable[[], gym.Env]], address: str | None = None,
                 resources: dict[str, float] | None = None) -> None:
        """``resources``: the custom Ray resources each env holds (its node's CARLA server)."""
        self._stack = ExitStack()
        ray = self._ray = self._stack.enter_context(ray_session(address, len(env_fns), resources))
        self._watch = HeadWatch.of(ray, address)
        remote = ray.remote(num_cpus=1)(EnvActor)
        paths = driver_paths()
        self.actors = [remote.options(resources=resources or {}).remote(fn, paths) for fn in env_fns]
        self.closed = False
        self._lost = lost_errors(ray)
        self.nodes: list[tuple[str, str]] = []
        try:
            self.nodes = [(node_id, node_address(ray, node_id, ip))
                          for node_id, ip in self._get([a.where.remote() for a in self.actors])]
            observation_space, action_space = self._get(self.actors[0].spaces.remote())
        except BaseException:
            self._stack.close()  # a Ray this env started stops with it
            raise
        super().__init__(len(env_fns), observation_space, action_space)
        self._pending: list[Any] = []

    def step_async(self, actions: np.ndarray) -> None:
        self._pending = [a.step.remote(action) for a, action in zip(self.actors, actions, strict=True)]

    def step_wait(self) -> VecEnvStepReturn:
        results = self._get(self._pending)
        self._pending = []
        obs, rews, dones, infos, reset_infos = zip(*results, strict=True)
        self.reset_infos = list(reset_infos)
        return _stack_obs(obs, self.observation_space), np.stack(rews), np.stack(dones), list(infos)

    def reset(self) -> VecEnvObs:
        results = self._get([a.reset.remote(self._seeds[i], self._options[i]) for i, a in enumerate(self.actors)])
        obs, reset_infos = zip(*results, strict=True)
        self.reset_infos = list(reset_infos)
        self._reset_seeds()
        self._reset_options()
        return _stack_obs(obs, self.observation_space)

    def _get(self, refs: Any) -> Any:
        """``ray.get``, a lost actor or node raised as :class:`RayWorkersLost` naming the env and its node, a
        lost head as :class:`RayHeadLost` (the head is asked every second while the call waits)."""
        while True:
            try:
                return self._ray.get(refs, timeout=self._watch.every_s)
            except TimeoutError:  # Ray's GetTimeoutError is one
                self._watch.check()
            except self._lost as err:
                if getattr(err, "actor_init_failed", False):
                    raise  # the env failed to set up: its own error says why
                raise RayWorkersLost(self._describe_loss(err)) from None

    def _describe_loss(self, err: BaseException) -> str:
        self._watch.confirm()  # a lost head takes its envs with it, and node_alive would wait on its GCS
        gone = [i for i, (node_id, _) in enumerate(self.nodes) if not node_alive(self._ray, node_id)]
        if gone:
            nodes = sorted({f"{self.nodes[i][0]} ({self.nodes[i][1]})" for i in gone})
            return f"lost Ray node {', '.join(nodes)} with training env(s) {', '.join(map(str, gone))}"
        first = str(err).strip().splitlines()
        return f"a Ray training env's worker died ({type(err).__name__}: {first[0][:160] if first else ''})"

    def close(self) -> None:
        if self.closed:
            return
        if not self._watch.lost:  # with a lost head the call would wait on its GCS
            try:
                self._ray.get([a.close.remote() for a in self.actors], timeout=60)
            except Exception:  # noqa: BLE001 - a dead actor has nothing to close
                pass
        self.closed = True
        self._stack.close()

    def _targets(self, indices: VecEnvIndices) -> list[Any]:
        return [self.actors[i] for i in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return self._get([a.get_attr.remote(attr_name) for a in self._targets(indices)])

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._get([a.set_attr.remote(attr_name, value) for a in self._targets(indices)])

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        return self._get([a.env_method.remote(method_name, method_args, method_kwargs)
                              for a in self._targets(indices)])

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return self._get([a.is_wrapped.remote(wrapper_class) for a in self._targets(indices)])

    def get_images(self) -> Sequence[np.ndarray | None]:
        return self.env_method("render")


