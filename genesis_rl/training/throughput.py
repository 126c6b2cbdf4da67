"""Where the trainer's CPU time goes, arranged so that 2 cores do the paper's schedule in under 10 minutes.

Two phases alternate and want different things (measured on 2 cores, docs/benchmarks.md):

- **Rollouts.** The envs step in their own processes (one torch thread each) and the trainer process only
  runs the policy on their observations, a batch of 2-4 small images. With torch's default of one thread
  per core, that forward pass wakes an OpenMP team that then spins against the env processes; one thread
  is faster for so small a batch and leaves the cores to the simulators.
- **The PPO update.** 320 minibatches of 64 images per update, each a forward and backward pass of the
  Nature CNN: here the trainer should have every core. The convolutions run in channels-last layout and
  Adam as one fused kernel, which together cut a minibatch by about a sixth.

Neither changes what the env or the system under test computes; they change the policy's floating-point
arithmetic slightly (results stay deterministic for a seed, and a resumed run takes the same path).
"""

from __future__ import annotations

from typing import Any

import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.torch_layers import NatureCNN


class ChannelsLastNatureCNN(NatureCNN):
    """SB3's Nature CNN (the same layers, parameters and state-dict keys) computed in channels-last layout,
    oneDNN's own: each batch of images is laid out so before the first convolution, and the weights from
    the first forward pass on (SB3's orthogonal initialisation and a loaded state dict both need them
    contiguous before; the parameters stay the same objects, so the optimizer keeps them)."""

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        for param in self.cnn.parameters():  # in place, as Module.to(memory_format=...) does; once
            if param.dim() == 4 and not param.is_contiguous(memory_format=torch.channels_last):
                param.data = param.data.contiguous(memory_format=torch.channels_last)
        return super().forward(observations.contiguous(memory_format=torch.channels_last))


def policy_kwargs(policy: str) -> dict[str, Any]:
    """policy_kwargs of a new PPO model: Adam as one fused kernel (torch >= 2.4 has it on the CPU) and, for
    the image policy (and its LSTM twin), the channels-last Nature CNN."""
    kwargs: dict[str, Any] = {"optimizer_kwargs": {"fused": True}}
    if policy in ("CnnPolicy", "CnnLstmPolicy"):
        kwargs["features_extractor_class"] = ChannelsLastNatureCNN
    return kwargs


class RolloutThreads(BaseCallback):
    """One torch thread in this process while the envs (other processes) collect a rollout; ``update``
    threads (0: torch's default at start) for the PPO update in between."""

    def __init__(self, update: int = 0) -> None:
        super().__init__()
        self.update = update or torch.get_num_threads()

    def _on_rollout_start(self) -> None:
        torch.set_num_threads(1)

    def _on_rollout_end(self) -> None:
        torch.set_num_threads(self.update)

    def _on_training_end(self) -> None:
        torch.set_num_threads(self.update)

    def _on_step(self) -> bool:
        return True
