"""Systems under test with known in-ODD weaknesses, and controls without (docs/zoo.md)."""

from genesis_rl.sut.zoo.members import ZOO, ZooMember, env_settings, zoo_member
from genesis_rl.sut.zoo.trigger import EMPTY, Bound, TriggerRegion

__all__ = ["EMPTY", "ZOO", "Bound", "TriggerRegion", "ZooMember", "env_settings", "zoo_member"]
