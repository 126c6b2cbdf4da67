"""Rulebook and reward: a trajectory of step records -> per-rule violations -> the agent's reward."""

from genesis_rl.loop.rules.reward import PaperReward, RewardConfig
from genesis_rl.loop.rules.rulebook import RULES, Rule, Rulebook, load_rulebook, register_rule

__all__ = ["RULES", "PaperReward", "RewardConfig", "Rule", "Rulebook", "load_rulebook", "register_rule"]
