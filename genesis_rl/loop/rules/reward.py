"""The agent's reward from a step's rule terms and the detector's IoU.

Default (the paper): r_t = exp(-IoU_t) + ln(1 + w_c a_c + w_p a_p), with (w_c, w_p) = (500, 100), a_c the
collision term and a_p the proximity term of the step (see ``rulebook``), and IoU_t the frame IoU of
``genesis_rl.sim.geometry`` (1 when no vehicle is in view). The first term rewards hiding vehicles from
the detector, the second (log-damped) rewards the behaviour violations that follow. Other rules join the
log term by name through ``rule_weights``; ``naturalness_weight`` adds the weather change's surprise; a
weighted rule the rulebook lacks is an error when the reward is built, not a silent zero.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.loop.rules.rulebook import Rulebook


@dataclass(frozen=True)
class RewardConfig:
    collision_weight: float = 500.0  # w_c [1 / (m/s)]: weight of the rule named "collision"
    proximity_weight: float = 100.0  # w_p [1 / (m/s)]: weight of the rule named "proximity"
    iou_weight: float = 1.0  # scales exp(-IoU)
    rule_weights: dict[str, float] = field(default_factory=dict)  # more rules by name [1 / rule unit]
    naturalness_weight: float = 0.0  # scales the step's weather surprise (-0.5 sum z^2, odd.dynamics) [1/nat]

    def __post_init__(self) -> None:
        # every weight in [0, 1e6]: a rule term of 70 m/s times 1e6, summed over a few rules, stays finite
        for k in ("collision_weight", "proximity_weight", "iou_weight", "naturalness_weight"):
            v = getattr(self, k)
            if isinstance(v, int | float) and not isinstance(v, bool) and not (math.isfinite(v) and v >= 0):
                raise UserInputError(f"env.reward.{k} = {v} must be a finite number >= 0 (at most 1e6)")
            ranges.WEIGHT.check(v, f"env.reward.{k}")
        if not isinstance(self.rule_weights, Mapping):
            raise UserInputError(f"env.reward.rule_weights = {self.rule_weights!r} must be a table of rule weights")
        for name, w in self.rule_weights.items():
            if name in ("collision", "proximity"):
                raise UserInputError(f"env.reward.rule_weights.{name}: set it with env.reward.{name}_weight")
            ranges.WEIGHT.check(w, f"env.reward.rule_weights.{name}")

    def weights(self) -> dict[str, float]:
        """Every rule weight by rule name, the paper's two first."""
        return {"collision": self.collision_weight, "proximity": self.proximity_weight,
                **{k: float(v) for k, v in self.rule_weights.items()}}


class PaperReward:
    """r = iou_weight * exp(-IoU) + ln(1 + sum_rule w_rule * term_rule); ``terms`` returns every part for
    ``info``. With a ``rulebook``, every rule with a weight > 0 must be in it."""

    def __init__(self, config: RewardConfig | None = None, rulebook: Rulebook | None = None) -> None:
        self.config = config or RewardConfig()
        self.weights = {k: w for k, w in self.config.weights().items() if w > 0}
        if rulebook is not None:
            missing = [k for k in self.weights if k not in rulebook.names]
            if missing:
                raise UserInputError(
                    f"the reward weights rule(s) {missing} that the rulebook lacks (it has "
                    f"{', '.join(rulebook.names)}); add them to the rulebook or set their weight to 0 "
                    "(reward.collision_weight, reward.proximity_weight, reward.rule_weights)")

    def terms(self, iou: float, rule_terms: Mapping[str, float], surprise: float = 0.0) -> dict[str, float]:
        """Every part of the step's reward. ``surprise``: the weather change's log-likelihood less that of no
        change (<= 0, ``odd.dynamics.WeatherModel.surprise``); with ``naturalness_weight`` > 0 it joins the
        reward as ``reward_naturalness``, so the agent searches for the most likely failure (AST)."""
        perception = self.config.iou_weight * math.exp(-iou)
        behaviour = math.log1p(sum(w * float(rule_terms.get(k, 0.0)) for k, w in self.weights.items()))
        out = {"reward_perception": perception, "reward_behaviour": behaviour, "reward": perception + behaviour}
        if self.config.naturalness_weight > 0:
            out["reward_naturalness"] = self.config.naturalness_weight * surprise
            out["reward"] += out["reward_naturalness"]
        return out
