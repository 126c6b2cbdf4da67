"""The careful-driver reference: could a competent and careful human driver have avoided a collision
that an actor knob caused (a neighbour cutting in, the lead braking)?

A collision the tester caused with another road user is a failure of the system only when a careful driver in
the ego's place would have avoided it; otherwise the tester, not the system, made the crash (an unavoidable
cut-in is never counted against the system). The reference is UN Regulation No. 157 (ALKS), Annex 4
Appendix 3, "competent and careful human driver", with the figures as esmini's R157 reference driver
implements them (``ControllerALKS_R157SM``):

- *perception*: a cut-in can be perceived once the cutter has wandered 0.375 m toward the ego's lane
  (``ActorEvent.perceivable_s``, measured by the simulator), a braking lead at its onset (its brake lights);
  the risk then takes 0.4 s to perceive;
- *criticality*: a braking lead is critical as soon as it is perceived (esmini's ``alwaysTrigOnScenario``); a
  cut-in only once the time-to-collision or the time headway falls under 2 s (esmini's criterion), checked
  from the end of the perception time on; the speed is held until then. Gating a braking lead on the headway
  as well punished a longer gap: a driver 2.5-3.5 s behind a lead braking to a stop at 4-6 m/s^2 held its speed
  until the headway fell under 2 s and then hit the much slower lead, where one 1.5-2 s behind reacted at once
  and stopped in time (``tests/test_cut_in.py``);
- *reaction*: 0.75 s more before the brake acts; the speed is held meanwhile;
- *braking*: the deceleration rises at 12.65 m/s^3 to 0.774 g (7.59 m/s^2, reached after 0.6 s) and is held
  until the car stops.

The reference drives as the recorded ego did until the actor is in its path (after the event became
perceivable), then takes over at the ego's position and speed there and closes on the actor along the path:
the actor moves as recorded (its gap and speed on the steps it was the ego's lead) and, after the recorded
impact, as it moved just before (constant deceleration, never backwards). It collides when its gap to the
actor reaches zero on a step the actor was in its path; an actor never in the path before the impact (a side
impact) is a collision no braking avoids. One-dimensional: swerving is not
credited (R157's driver brakes), and lateral motion after the event counts only through "in the path".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from genesis_rl.sim.interface import ActorEvent
from genesis_rl.world.step_record import StepRecord

G = 9.81
#: the longest the reference is followed past the recorded impact [s] (it has stopped long before)
HORIZON_S = 30.0
#: the actor's extrapolated acceleration after the impact is clipped to this range [m/s^2]
ACTOR_ACCEL_RANGE = (-8.0, 2.0)


@dataclass(frozen=True)
class CarefulDriver:
    """R157's competent and careful driver (module docstring): perception and reaction times [s], the
    deceleration it brakes at [m/s^2] and how fast it gets there [m/s^3]."""

    name: str = "UN R157 careful driver (a braking lead critical once perceived)"
    perception_s: float = 0.4
    reaction_s: float = 0.75
    max_decel: float = 0.774 * G
    jerk: float = 0.774 * G / 0.6
    critical_ttc_s: float = 2.0
    critical_headway_s: float = 2.0
    #: events critical as soon as they are perceived, without the time-to-collision or headway gate
    always_critical: tuple[str, ...] = ("lead_braking",)

    def critical(self, gap: float, speed: float, actor_speed: float) -> bool:
        """Whether a gap [m] at these speeds [m/s] is critical: time-to-collision or time headway under 2 s."""
        closing = speed - actor_speed
        return ((closing > 0.0 and gap / closing < self.critical_ttc_s)
                or (speed > 0.0 and gap / speed < self.critical_headway_s))

    def decel_at(self, since_brake_s: float) -> float:
        """Its deceleration [m/s^2] ``since_brake_s`` after the brake starts to act (0 before)."""
        return 0.0 if since_brake_s <= 0.0 else min(self.max_decel, self.jerk * since_brake_s)


R157 = CarefulDriver()


#: an actor event this long [s] or less before an impact with its vehicle made that collision the tester's
#: doing (the reference decides it, and clustering names it: ``distinct.what_was_hit``)
ACTOR_EVENT_WINDOW_S = 10.0


def event_for_collision(events: Sequence[ActorEvent], records: Sequence[StepRecord], hit_at: int,
                        window_s: float = ACTOR_EVENT_WINDOW_S) -> ActorEvent | None:
    """The first actor event with the vehicle the ego hit at ``records[hit_at]`` that began within ``window_s``
    before the impact (None: the tester did not act on that vehicle). The first, since a careful driver
    perceived the actor from then on (a lead braked again after a pause was already being watched); when to
    react is the criticality check's to say."""
    hit = records[hit_at]
    mine = [e for e in events if e.vehicle_id == hit.collision.other_id
            and hit.time_s - window_s <= e.onset_s <= hit.time_s + 1e-9]
    return min(mine, key=lambda e: e.onset_s) if mine else None


def careful_driver_evidence(records: Sequence[StepRecord], hit_at: int, event: ActorEvent, dt: float,
                            driver: CarefulDriver = R157) -> dict[str, Any]:
    """Would ``driver`` in the ego's place have hit the actor of ``event``? The evidence: when it perceived
    the event and started braking, the speed it had, the smallest gap it kept and whether it collides."""
    actor = event.vehicle_id
    t_hit = records[hit_at].time_s
    t_seen = event.perceivable_s if event.perceivable_s is not None else t_hit
    out: dict[str, Any] = {"reference": driver.name, "event": event.kind, "onset_s": round(event.onset_s, 3),
                           "perceivable_s": None if event.perceivable_s is None else round(t_seen, 3)}
    k_seen = next((i for i in range(hit_at + 1) if records[i].time_s >= t_seen - 1e-9), hit_at)
    perceived = records[k_seen].time_s + driver.perception_s
    # it drives as the ego did until the actor is in its path: before that the actor is no hazard, and the
    # traffic ahead (which this one-dimensional reference does not see) set the pace
    k0 = next((i for i in range(k_seen, hit_at) if records[i].lead.vehicle_id == actor), hit_at)
    brake_at = math.inf  # set once the situation is critical, after the perception time
    v_ref = float(records[k0].ego.speed)
    out["speed_m_s"] = round(v_ref, 3)

    always = event.kind in driver.always_critical

    def check_critical(t: float, gap: float, actor_speed: float) -> None:
        nonlocal brake_at
        if math.isinf(brake_at) and t >= perceived - 1e-9 and (always or driver.critical(gap, v_ref, actor_speed)):
            brake_at = t + driver.reaction_s

    x_rec = x_ref = 0.0  # distance driven since records[k0]: by the recorded ego, by the reference
    min_gap = math.inf
    collides_at: float | None = None
    last: tuple[float, float, float, float] | None = None  # (time, actor position, its speed, its acceleration)
    for i in range(k0, hit_at):  # the steps before the recorded impact: the actor as recorded
        r = records[i]
        if i > k0:
            x_rec += 0.5 * (records[i - 1].ego.speed + r.ego.speed) * dt
            v_ref, x_ref = _advance(driver, v_ref, x_ref, r.time_s - dt, brake_at, dt)
        if r.lead.vehicle_id != actor or not math.isfinite(r.lead.true_distance):
            continue  # not in the path (yet): nothing to hit
        position = x_rec + r.lead.true_distance
        gap = position - x_ref
        accel = 0.0 if last is None else (r.lead.speed - last[2]) / max(r.time_s - last[0], dt)
        last = (r.time_s, position, float(r.lead.speed), accel)
        check_critical(r.time_s, gap, float(r.lead.speed))
        min_gap = min(min_gap, gap)
        if gap <= 0.0 and collides_at is None:
            collides_at = r.time_s
    if collides_at is None and last is not None:  # past the impact: the actor goes on as it went before it
        t_a, position, v_a, accel = last
        a_a = min(max(accel, ACTOR_ACCEL_RANGE[0]), ACTOR_ACCEL_RANGE[1])
        t_ref = records[max(hit_at - 1, k0)].time_s  # where the loop above left the reference

        def actor_step() -> None:
            nonlocal position, v_a, t_a
            v_next = max(0.0, v_a + a_a * dt)
            position += 0.5 * (v_a + v_next) * dt
            v_a, t_a = v_next, t_a + dt

        while t_a < t_ref - 1e-9:  # bring the actor up to the reference's time
            actor_step()
        for _ in range(int(round((t_hit - t_ref + HORIZON_S) / dt))):
            actor_step()
            v_ref, x_ref = _advance(driver, v_ref, x_ref, t_ref, brake_at, dt)
            t_ref += dt
            gap = position - x_ref
            check_critical(t_ref, gap, v_a)
            min_gap = min(min_gap, gap)
            if gap <= 0.0:
                collides_at = t_ref
                break
            if v_ref <= 0.0:
                break
    elif last is None:  # the actor was never in the path before the impact: nothing to measure it by
        collides_at = t_hit
    out.update(critical_s=None if math.isinf(brake_at) else round(brake_at - driver.reaction_s, 3),
               brake_from_s=None if math.isinf(brake_at) else round(brake_at, 3),
               min_gap_m=None if not math.isfinite(min_gap) else round(min_gap, 3),
               collides=collides_at is not None,
               collision_s=None if collides_at is None else round(collides_at, 3))
    return out


def _advance(driver: CarefulDriver, v: float, x: float, t: float, brake_at: float, dt: float) -> tuple[float, float]:
    """The reference's speed and distance after one step from time ``t`` (the deceleration at mid-step: exact
    on the linear rise, so the stop does not move with the step length)."""
    v_next = max(0.0, v - driver.decel_at(t + 0.5 * dt - brake_at) * dt)
    return v_next, x + 0.5 * (v + v_next) * dt
