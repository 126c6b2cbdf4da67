"""The agent's reward from a step's rule terms and the detector's IoU.

Default (the paper): r_t = exp(-IoU_t) + ln(1 + w_c a_c + w_p a_p), with (w_c, w_p) = (500, 100), a_c the
collision term and a_p the proximity term of the step (see ``rulebook``), and IoU_t the frame IoU of
``genesis_rl.sim.geometry`` (1 when no vehicle is in view). The first term rewards hiding vehicles from
the detector, the second (log-damped) rewards the behaviour violations that follow. Other rules join the
log term by name through ``rule_weights``; ``naturalness_weight`` adds the weather change's surprise; a
weighted rule the rulebook lacks is an error when the reward is built, not a silent zero.

``objective = "falsification"`` pays for the failure itself, as Adaptive Stress Testing does (Lee et al., JAIR
2020): the episode ends at the first in-ODD collision, which pays ``failure_reward``; until then each step pays
``closeness_weight`` times the rise of the episode's worst danger (``loop.rules.danger``: how hard the ego would
have to brake to stop behind its lead; potential-based, so an episode's shaping sums to its worst danger, dense
near a failure and never more than a quarter of one), the detector's loss scaled so that a whole episode of it
pays at most ``perception_cap``, and the naturalness term. A near miss can no longer outscore a collision: on
the paper's reward a near miss earned 127.5 against a collision's 169 on the same scene (docs/adversaries.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.loop.rules.danger import COLLISION_DANGER, danger
from genesis_rl.loop.rules.rulebook import Rulebook
from genesis_rl.world.odd.domain import IN_ODD
from genesis_rl.world.step_record import StepRecord

#: ``RewardConfig.objective``: the paper's reward, or the failure itself
OBJECTIVES = ("paper", "falsification")


@dataclass(frozen=True)
class RewardConfig:
    collision_weight: float = 500.0  # w_c [1 / (m/s)]: weight of the rule named "collision"
    proximity_weight: float = 100.0  # w_p [1 / (m/s)]: weight of the rule named "proximity"
    iou_weight: float = 1.0  # scales exp(-IoU)
    rule_weights: dict[str, float] = field(default_factory=dict)  # more rules by name [1 / rule unit]
    naturalness_weight: float = 0.0  # scales the step's weather surprise (-0.5 sum z^2, odd.dynamics) [1/nat]
    objective: str = "paper"  # paper, or falsification: the failure pays, the episode ends there (module doc)
    failure_reward: float = 100.0  # falsification: the first in-ODD collision's reward
    closeness_weight: float = 10.0  # falsification: per unit of the episode's worst danger (at most 2.5)
    perception_cap: float = 10.0  # falsification: the most a whole episode of the detector's loss pays

    def __post_init__(self) -> None:
        if self.objective not in OBJECTIVES:
            raise UserInputError(f"env.reward.objective = {self.objective!r}; allowed: {', '.join(OBJECTIVES)}")
        for k in ("failure_reward", "closeness_weight", "perception_cap"):
            ranges.WEIGHT.check(getattr(self, k), f"env.reward.{k}")
        if self.objective == "falsification" and \
                self.closeness_weight * COLLISION_DANGER + self.perception_cap >= self.failure_reward:
            raise UserInputError(
                f"env.reward: closeness_weight x {COLLISION_DANGER} + perception_cap = "
                f"{self.closeness_weight * COLLISION_DANGER + self.perception_cap:g} must stay under failure_reward = "
                f"{self.failure_reward:g}, or an episode without a failure could outscore one with it")
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

    def reset(self) -> None:
        """A new episode (the paper's reward keeps nothing between steps)."""

    def is_failure(self, rec: StepRecord) -> bool:
        """Whether this step ends the episode (never: the paper runs every episode for its full length)."""
        return False

    def step_terms(self, rec: StepRecord, rule_terms: Mapping[str, float], surprise: float = 0.0) -> dict[str, float]:
        """Every part of a step's reward, from its record."""
        return self.terms(rec.iou, rule_terms, surprise)

    def terms(self, iou: float, rule_terms: Mapping[str, float], surprise: float = 0.0) -> dict[str, float]:
        """Every part of the step's reward. ``surprise``: the weather change's log-likelihood less that of no
        change (<= 0, ``odd.dynamics.WeatherModel.surprise``); with ``naturalness_weight`` > 0 it joins the
        reward as ``reward_naturalness``, so the agent searches for the most likely failure (AST)."""
        perception = self.config.iou_weight * math.exp(-iou)
        behaviour = math.log1p(sum(w * float(rule_terms.get(k, 0.0)) for k, w in self.weights.items()))
        return self._with_naturalness(
            {"reward_perception": perception, "reward_behaviour": behaviour, "reward": perception + behaviour},
            surprise)

    def _with_naturalness(self, out: dict[str, float], surprise: float) -> dict[str, float]:
        """``out`` with the naturalness term joined (``naturalness_weight`` > 0), whichever objective built it."""
        if self.config.naturalness_weight > 0:
            out["reward_naturalness"] = self.config.naturalness_weight * surprise
            out["reward"] += out["reward_naturalness"]
        return out


class FalsificationReward(PaperReward):
    """The failure itself (``objective = "falsification"``, see the module docstring). Keeps the episode's worst
    danger, so it is reset per episode and snapshotted with it."""

    def __init__(self, config: RewardConfig, rulebook: Rulebook | None = None, episode_steps: int = 512,
                 with_odd: bool = True) -> None:
        super().__init__(replace(config, collision_weight=0.0, proximity_weight=0.0, rule_weights={}), rulebook)
        self.episode_steps = max(1, int(episode_steps))
        self.with_odd = with_odd
        self.worst = 0.0

    def reset(self) -> None:
        self.worst = 0.0

    def is_failure(self, rec: StepRecord) -> bool:
        """A collision inside the ODD (on its boundary included); any collision when no ODD is declared."""
        return rec.collision.collided and (not self.with_odd or rec.odd_status in IN_ODD)

    def step_terms(self, rec: StepRecord, rule_terms: Mapping[str, float], surprise: float = 0.0) -> dict[str, float]:
        c = self.config
        now = max(self.worst, danger(rec))
        closeness = c.closeness_weight * (now - self.worst)
        self.worst = now
        perception = c.perception_cap / self.episode_steps * math.exp(-rec.iou)
        failure = c.failure_reward if self.is_failure(rec) else 0.0
        return self._with_naturalness({"reward_perception": perception, "reward_closeness": closeness,
                                       "reward_failure": failure, "reward": perception + closeness + failure},
                                      surprise)


def make_reward(config: RewardConfig, rulebook: Rulebook, episode_steps: int, with_odd: bool) -> PaperReward:
    """The reward ``config.objective`` names."""
    if config.objective == "falsification":
        return FalsificationReward(config, rulebook, episode_steps, with_odd)
    return PaperReward(config, rulebook)
