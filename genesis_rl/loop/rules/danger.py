"""How close a step came to a rear-end collision: the deceleration the ego would need to stop behind its lead,
over a hard braking's. One measure for the falsification reward's shaping and Go-Explore's promise, so that what
the agent is paid for and what the explorer returns to are the same thing."""

from __future__ import annotations

import math

from genesis_rl.world.step_record import StepRecord

#: the deceleration a hard braking demands [m/s^2]: a danger of 1 needs that much to stop behind the lead
HARD_BRAKING = 6.0
#: a lead the system misses within this range [m] adds MISS_DANGER: what the system is about to miss (about
#: three seconds at urban speed)
MISS_RANGE_M, MISS_DANGER = 40.0, 0.5
#: the most a step without a collision can score, and a collision's score
MAX_DANGER = 2.0
COLLISION_DANGER = MAX_DANGER + MISS_DANGER


def danger(rec: StepRecord) -> float:
    """The needed deceleration over a hard braking's (0: none needed or no lead; 1: a hard braking; capped at
    ``MAX_DANGER``), plus ``MISS_DANGER`` when the system does not see a lead within ``MISS_RANGE_M`` that is in
    the picture; a collision scores ``COLLISION_DANGER``."""
    if rec.collision.collided:
        return COLLISION_DANGER
    gap, lead_speed = rec.lead.true_distance, rec.lead.speed
    if not (rec.lead.present and math.isfinite(gap) and math.isfinite(lead_speed)):
        return 0.0
    missed = MISS_DANGER if rec.lead.detected is False and gap < MISS_RANGE_M else 0.0
    closing = rec.ego.speed - lead_speed
    if closing <= 0.0:
        return missed
    return min(MAX_DANGER, closing * closing / (2.0 * max(gap, 0.1)) / HARD_BRAKING) + missed
