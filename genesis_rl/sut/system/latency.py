"""The built-in system behind a slow perception pipeline: its detections reach the controller late, and some
frames are dropped (the timing kind of weakness).

Real perception stacks answer tens to hundreds of milliseconds after the exposure (camera read-out, inference,
tracking, the bus), and drop frames under load. The controller then acts on where the lead *was*. In steady
following that costs nothing a time gap does not absorb; it matters when the lead brakes hard, which is what
makes the weakness one of timing (docs/zoo.md). The delay is a whole number of 0.05 s steps; a dropped frame
delivers no detections, and the controller holds its track as it does for a missed one. Drops are drawn
from the episode's seed, so an episode replays exactly.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from genesis_rl.core import ranges
from genesis_rl.sim.interface import ActorState, SensorFrame
from genesis_rl.sut.system.builtin import BuiltinSystem
from genesis_rl.sut.system.controller import ControllerConfig
from genesis_rl.sut.system.protocol import Detection, EpisodeContext, SystemOutput


class LatencySystem(BuiltinSystem):
    """:class:`BuiltinSystem` whose detections arrive ``latency_s`` late; each frame is lost with
    probability ``drop_rate``."""

    def __init__(self, latency_s: float = 0.3, drop_rate: float = 0.0, weights: str | None = None,
                 score_threshold: float | None = None,
                 controller: ControllerConfig | dict[str, Any] | None = None) -> None:
        super().__init__(weights, score_threshold, controller)
        self.latency_s = float(ranges.number(latency_s, "system latency_s", 0.0, 5.0, "s"))
        self.drop_rate = float(ranges.number(drop_rate, "system drop_rate", 0.0, 1.0,
                                             note="the share of frames lost"))
        self._queue: deque[list[Detection]] = deque()
        self._delay_steps = 0
        self._rng = np.random.default_rng(0)

    def reset(self, context: EpisodeContext) -> None:
        super().reset(context)
        self._delay_steps = int(round(self.latency_s / context.dt))
        self._queue = deque()
        self._rng = np.random.default_rng(np.random.SeedSequence([context.seed, 0x1A7E]))

    def step(self, frame: SensorFrame, ego: ActorState, time_s: float) -> SystemOutput:
        fresh = self.perceive(frame)
        if self.drop_rate > 0.0 and self._rng.random() < self.drop_rate:
            fresh = []
        if not self._queue:  # the episode's first frame: the pipeline ran before the scene began, so what it
            # delivers until its first delayed frame arrives is (about) this frame, not an empty road. Empty
            # detections there made the controller accelerate blind for latency_s at every episode's start.
            self._queue.extend([fresh] * self._delay_steps)
        self._queue.append(fresh)
        arrived = self._queue.popleft()
        control, gap = self.controller.step(ego, arrived, time_s)
        return SystemOutput(control, arrived, gap, self.controller.status)

    def identity(self) -> dict[str, Any]:
        return {**super().identity(), "latency_s": self.latency_s, "drop_rate": self.drop_rate}
