"""The built-in system with a controller that slows for the visibility it perceives (the benchmark's competent
controller whose weakness is one of timing).

Each frame it estimates the visibility from its camera (:mod:`genesis_rl.sut.system.visibility`) and caps its cruise
speed so that it can stop within the distance at which its detector still finds a car, a fraction of that
visibility: ``v t_r + v^2 / (2 b) <= sight_fraction x visibility``. The default fraction, 0.3 of the estimate
(about 0.2 of the true visibility, the estimator reading low), is where the built-in detector still finds a
lead on lite's highway (docs/zoo.md: at 50 m of visibility it finds 85 % of leads within 10 m, 9 % at
10-20 m). In steady fog it is careful, so a lead that brakes hard appears in time.

The estimate is smoothed over ``smoothing_s`` (in log space, as a real estimator damps its flicker): when fog
thickens quickly, the speed follows seconds late, and a lead braking in that window appears too close. The
smoothing is the planted weakness of the ``fog_braking`` zoo member; its control smooths over 0.5 s.
"""

from __future__ import annotations

import math
from typing import Any

from genesis_rl.core import ranges
from genesis_rl.sim.interface import ActorState, SensorFrame
from genesis_rl.sut.system.builtin import BuiltinSystem
from genesis_rl.sut.system.controller import ControllerConfig
from genesis_rl.sut.system.protocol import EpisodeContext, SystemOutput
from genesis_rl.sut.system.visibility import CLEAR_AIR_M, estimate_visibility


def speed_for_sight(sight_m: float, reaction_s: float, decel: float) -> float:
    """The largest speed [m/s] that stops within ``sight_m``: ``v t_r + v^2 / (2 b) = sight``."""
    return -decel * reaction_s + math.sqrt((decel * reaction_s) ** 2 + 2.0 * decel * max(sight_m, 0.0))


class AdaptiveSystem(BuiltinSystem):
    """:class:`BuiltinSystem` whose cruise speed is capped by the visibility it estimates, smoothed over
    ``smoothing_s``."""

    def __init__(self, smoothing_s: float = 0.5, sight_fraction: float = 0.3, reaction_s: float = 0.5,
                 decel: float = 5.0, weights: str | None = None, score_threshold: float | None = None,
                 controller: ControllerConfig | dict[str, Any] | None = None) -> None:
        super().__init__(weights, score_threshold, controller)
        self.smoothing_s = float(ranges.number(smoothing_s, "system smoothing_s", 0.0, 60.0, "s"))
        self.sight_fraction = float(ranges.number(sight_fraction, "system sight_fraction", 0.05, 2.0,
                                                  note="the share of the visibility at which a car is detected"))
        self.reaction_s = float(ranges.number(reaction_s, "system reaction_s", 0.0, 5.0, "s"))
        self.decel = float(ranges.number(decel, "system decel", 0.5, 10.0, "m/s^2"))
        self.visibility_m = CLEAR_AIR_M  # the smoothed estimate
        self._started = False

    def reset(self, context: EpisodeContext) -> None:
        super().reset(context)
        self._started = False
        self.visibility_m = CLEAR_AIR_M
        self.controller.speed_cap = math.inf

    def _update_visibility(self, frame: SensorFrame) -> None:
        assert self.context is not None
        seen = estimate_visibility(frame.rgb, frame.depth, self.context.camera.max_range)
        if seen is None:
            return  # nothing to tell from this frame: keep the estimate
        if not self._started:  # the estimator ran before the scene began: it starts settled
            self.visibility_m, self._started = seen, True
            return
        alpha = 1.0 if self.smoothing_s <= 0.0 else 1.0 - math.exp(-self.context.dt / self.smoothing_s)
        log_now = math.log(self.visibility_m)
        self.visibility_m = math.exp(log_now + alpha * (math.log(seen) - log_now))

    def step(self, frame: SensorFrame, ego: ActorState, time_s: float) -> SystemOutput:
        self._update_visibility(frame)
        self.controller.speed_cap = speed_for_sight(self.sight_fraction * self.visibility_m, self.reaction_s,
                                                    self.decel)
        return super().step(frame, ego, time_s)

    def identity(self) -> dict[str, Any]:
        return {**super().identity(), "smoothing_s": self.smoothing_s, "sight_fraction": self.sight_fraction,
                "reaction_s": self.reaction_s, "decel": self.decel}
