"""How lite realises the actor knobs on one vehicle: a braking lead's speed and a cut-in's lateral path.

Pure kinematics over one step, as references for tests on crafted scenes: ``Traffic.step`` realises the
lead's braking itself (``forced_braking``, the same profile) and the cut-in by pure pursuit; placing the
cutter at ``cut_in_start_gap`` and following ``cut_in_offset`` is not wired yet (docs/actors.md).
"""

from __future__ import annotations

import math

CUT_IN_DURATION = 3.0  # lane change time [s] (assumed; naturalistic lane changes take some seconds)


def lead_speed(speed: float, t: float, decel: float, onset: float, dt: float) -> float:
    """The lead's speed after a step of ``dt`` from time ``t``: it brakes at ``decel`` m/s^2 from ``onset``
    (the part of the step after onset), never below standstill."""
    braking = max(0.0, min(t + dt, math.inf) - max(t, onset))
    return max(0.0, speed - decel * braking)


def cut_in_offset(t: float, onset: float, lane_width: float, duration: float = CUT_IN_DURATION) -> float:
    """Lateral distance [m] still to go into the ego's lane at time ``t``: ``lane_width`` before onset,
    a smooth (cosine) path to 0 over ``duration`` s, then 0 (the cutter is centred in the ego's lane)."""
    u = min(1.0, max(0.0, (t - onset) / duration))
    return lane_width * 0.5 * (1.0 + math.cos(math.pi * u))


def cut_in_start_gap(ego_speed: float, cutter_speed: float, ttc: float, duration: float = CUT_IN_DURATION) -> float:
    """The longitudinal gap [m] at onset that leaves a gap of ``ttc`` times the closing speed when the
    cutter reaches the ego's lane (both at constant speed)."""
    return (ego_speed - cutter_speed) * (ttc + duration)
