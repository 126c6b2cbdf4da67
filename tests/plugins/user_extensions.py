"""A user's own extensions, outside the package, as docs/extending.md shows them: a rule named by import
path in a rulebook TOML, and a weather policy registered with a decorator (resolved in worker processes)."""

from __future__ import annotations

import numpy as np

from genesis_rl.adversaries import StepPolicy, register_policy
from genesis_rl.loop.rules.rulebook import Rule


class Speeding(Rule):
    """The ego's speed above ``limit`` [m/s], summed over the steps."""

    name = "speeding"
    description = "ego speed above the limit [m/s]"
    unit = "m/s"
    limit: float = 8.0  # [m/s]

    def term(self, record):
        return max(0.0, record.ego.speed - self.limit)


@register_policy
class FogRamp(StepPolicy):
    """Fog up every step, the other knobs still: the simplest open-loop schedule."""

    name = "fog_ramp"

    def act(self, obs):
        a = np.zeros(self.context.action_dim, np.float32)
        a[0] = 1.0
        return a
