"""The agent's reward from a step's rule terms and the detector's IoU.

Default (the paper): r_t = exp(-IoU_t) + ln(1 + w_c a_c + w_p a_p), with (w_c, w_p) = (500, 100), a_c the
collision term and a_p the proximity term of the step (see ``rulebook``), and IoU_t the frame IoU of
``genesis_rl.geometry`` (1 when no vehicle is in view). The first term rewards hiding vehicles from
the detector, the second (log-damped) rewards the behaviour violations that follow.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class RewardConfig:
    collision_weight: float = 500.0  # w_c [1 / (m/s)]
    proximity_weight: float = 100.0  # w_p [1 / (m/s)]
    iou_weight: float = 1.0  # scales exp(-IoU)

    def __post_init__(self) -> None:
        for k in ("collision_weight", "proximity_weight", "iou_weight"):
            if not (math.isfinite(getattr(self, k)) and getattr(self, k) >= 0):
                raise ValueError(f"reward.{k} = {getattr(self, k)} must be a finite number >= 0")


class PaperReward:
    """r = iou_weight * exp(-IoU) + ln(1 + w_c a_c + w_p a_p); ``terms`` returns every part for ``info``."""

    def __init__(self, config: RewardConfig | None = None) -> None:
        self.config = config or RewardConfig()

    def terms(self, iou: float, rule_terms: Mapping[str, float]) -> dict[str, float]:
        c = self.config
        a_c = float(rule_terms.get("collision", 0.0))
        a_p = float(rule_terms.get("proximity", 0.0))
        perception = c.iou_weight * math.exp(-iou)
        behaviour = math.log1p(c.collision_weight * a_c + c.proximity_weight * a_p)
        return {"reward_perception": perception, "reward_behaviour": behaviour, "reward": perception + behaviour}
