"""The built-in system behind a camera whose stream stalls once an episode, at a moment the world draws: a
weakness only an adversary that watches the system can trigger reliably (a *reactive* zoo member).

Camera drivers and frame grabbers stall under bus or memory pressure: as the buffer fills, frames arrive twice
(a *stutter*, every other frame a repeat, for ``warning_s``), then the last buffer is re-delivered for
``stall_s`` until the stream recovers. A perception stack that does not check frame counters tracks a frozen
world through the stall: its boxes and the controller's gap stand still while the lead may not. A lead that
began braking hard during the stutter is, by the stall, slow and close, and the frozen picture tells the
controller the gap holds, so it is met too late; braking long before or after the stall is met in time (the
built-in controller at the highway profile brakes in time for the domain's 6 m/s^2; stopped behind a lead it
holds the brake until it sees the gap open, as stop-and-go ACC does, so a stall at a standstill is harmless).

The stutter's start is drawn from the episode's world seed (``EpisodeContext.seed``), uniformly in
[``earliest_s``, ``latest_s``), so no fixed schedule can know it; a tester sees it as the system's detections
repeating exactly on consecutive steps.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from genesis_rl.core import ranges
from genesis_rl.sim.interface import ActorState, SensorFrame, VehicleControl
from genesis_rl.sut.system.builtin import BuiltinSystem
from genesis_rl.sut.system.controller import ControllerConfig
from genesis_rl.sut.system.protocol import Detection, EpisodeContext, SystemOutput

#: stop-and-go ACC: slower than HOLD_SPEED [m/s] behind a lead closer than HOLD_GAP [m], the system brakes to a
#: standstill and holds it (as such systems do below walking pace), until it sees the gap open
HOLD_SPEED, HOLD_GAP = 2.0, 15.0


def stall_start(seed: int, earliest_s: float, latest_s: float) -> float:
    """When the episode of world seed ``seed`` begins to stutter [s of episode time]."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57A11]))
    return float(rng.uniform(earliest_s, latest_s))


class StallSystem(BuiltinSystem):
    """:class:`BuiltinSystem` whose camera re-delivers one frame for ``stall_s`` once an episode."""

    def __init__(self, stall_s: float = 2.5, warning_s: float = 3.0, earliest_s: float = 6.0,
                 latest_s: float = 24.0, weights: str | None = None, score_threshold: float | None = None,
                 controller: ControllerConfig | dict[str, Any] | None = None) -> None:
        super().__init__(weights, score_threshold, controller)
        self.stall_s = float(ranges.number(stall_s, "system stall_s", 0.0, 10.0, "s"))
        self.warning_s = float(ranges.number(warning_s, "system warning_s", 0.0, 10.0, "s"))
        self.earliest_s = float(ranges.number(earliest_s, "system earliest_s", 0.0, 600.0, "s"))
        self.latest_s = float(ranges.number(latest_s, "system latest_s", self.earliest_s, 600.0, "s",
                                            note="at least earliest_s"))
        self.stutter_s = self.start_s = self.end_s = math.inf
        self._held: list[Detection] = []
        self._frames = 0
        self._standing_gap: float | None = None

    def reset(self, context: EpisodeContext) -> None:
        super().reset(context)
        self.stutter_s = stall_start(context.seed, self.earliest_s, self.latest_s)
        self.start_s = self.stutter_s + self.warning_s
        self.end_s = self.start_s + self.stall_s
        self._held, self._frames, self._standing_gap = [], 0, None

    def repeats(self, time_s: float) -> bool:
        """Whether the frame delivered at ``time_s`` is the last one again (the stutter's odd frames, the stall)."""
        if self.start_s <= time_s < self.end_s:
            return True
        return self.stutter_s <= time_s < self.start_s and self._frames % 2 == 1

    def step(self, frame: SensorFrame, ego: ActorState, time_s: float) -> SystemOutput:
        # the same frame gives the same boxes: keep them rather than run the detector on a copy
        detections = self._held if self._frames and self.repeats(time_s) else self.perceive(frame)
        self._held = detections
        self._frames += 1
        control, gap = self.controller.step(ego, detections, time_s)
        return SystemOutput(self._standstill_hold(control, ego, gap), detections, gap, self.controller.status)

    def _standstill_hold(self, control: VehicleControl, ego: ActorState, gap: float | None) -> VehicleControl:
        """Stop-and-go ACC: stopped behind a lead, keep the brake on until the perceived gap opens by a metre."""
        if self._standing_gap is None and ego.speed < HOLD_SPEED and gap is not None and gap < HOLD_GAP:
            self._standing_gap = gap
        if self._standing_gap is not None:
            if gap is None or gap > self._standing_gap + 1.0:
                self._standing_gap = None
            else:
                return VehicleControl(throttle=0.0, brake=1.0, steer=control.steer)
        return control

    def identity(self) -> dict[str, Any]:
        return {**super().identity(), "stall_s": self.stall_s, "warning_s": self.warning_s,
                "earliest_s": self.earliest_s, "latest_s": self.latest_s}
