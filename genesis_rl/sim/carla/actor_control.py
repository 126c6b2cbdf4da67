"""The actor knobs on a CARLA server: ``lead_decel`` by per-actor control, ``cut_in_ttc`` and the
surrounding traffic's behaviour by the traffic manager's own calls.

CARLA's TrafficManager has no "brake now at X m/s^2" call, so the braking lead leaves the traffic manager
(``SetAutopilot(False)``) and is given each tick a target velocity that is its current one shortened by
``lead_decel * dt``, along its own direction (``ApplyTargetVelocity``, applied before the physics step).
When the knob returns to 0 the vehicle rejoins the traffic manager. The lead is the one ahead of the ego when
the knob rises (``CarlaSimulation.lead``), as on lite; it stays the braking vehicle until the knob is 0.

Physics then acts on the commanded velocity (tyre friction, slopes), so the realised deceleration on a
server can differ from the demand by what one tick of physics adds; on lite it is exact.

The cut-in (:class:`CutIn`) picks the vehicle with the rule lite uses (``actor_knobs.pick_cut_in``) among the
vehicles ahead in the ego's neighbouring lanes, and asks the traffic manager to move it over
(``force_lane_change(actor, direction)``: True is the lane on the right, as the traffic manager's keep-right
rule uses it in ``LocalizationStage``). The traffic manager then changes lanes when it finds room; the event's
onset is when it was asked, and a careful driver can perceive it once the car has wandered 0.375 m.
With ``cut_in_relative_speed`` > 0 the nearest of those vehicles first gets ready: the traffic manager is given
its desired speed, that much under the ego's but not under half its speed limit (``set_desired_speed``, km/h),
so its gap closes as on lite; the
cutter keeps the speed it crossed at until the knob is back at its default, when each vehicle held is given
the traffic's ``vehicle_percentage_speed_difference`` again (which clears a desired speed in the traffic
manager's ``Parameters::SetPercentageSpeedDifference``).

:class:`TrafficBehaviour` sends ``vehicle_percentage_speed_difference`` and ``ignore_lights_percentage`` to the
traffic manager for every NPC when a value changes (nothing at their defaults).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

from genesis_rl.sim.interface import ActorEvent, LeadInfo
from genesis_rl.world.actor_knobs import CUT_IN_WANDER_M, pick_cut_in, pick_preparing, preparing_speed

#: the actor knobs a CARLA simulation realises
CARLA_ACTOR_KNOBS: tuple[str, ...] = ("lead_decel", "cut_in_ttc", "vehicle_percentage_speed_difference",
                                      "ignore_lights_percentage", "cut_in_relative_speed")
#: the traffic manager's per-vehicle calls, under the knobs' own names, with the knobs' defaults
TM_BEHAVIOUR_KNOBS: dict[str, float] = {"vehicle_percentage_speed_difference": 0.0, "ignore_lights_percentage": 0.0}


class LeadBraking:
    """State of the ``lead_decel`` knob on one CARLA episode: which vehicle brakes (scene index, -1: none)."""

    def __init__(self) -> None:
        self.vehicle = -1

    def commands(self, carla: Any, tm_port: int, decel: float, dt: float, lead: Callable[[], LeadInfo | None],
                 actor_id: Callable[[int], int | None], velocity: Callable[[int], tuple[float, float, float]]
                 ) -> list[Any]:
        """The batch of ``carla.command`` to send before the next tick. ``tm_port``: the traffic manager the
        vehicle leaves and rejoins; ``lead`` finds the ego's leader (asked only when braking starts),
        ``actor_id`` maps a scene index to the server's actor id (None: gone), ``velocity`` gives a vehicle's
        current velocity [m/s] (x, y, z)."""
        if decel <= 0.0:
            if self.vehicle < 0:
                return []
            aid, self.vehicle = actor_id(self.vehicle), -1
            return [] if aid is None else [carla.command.SetAutopilot(aid, True, tm_port)]
        out: list[Any] = []
        if self.vehicle < 0:
            found = lead()
            if found is None:
                return []
            self.vehicle = int(found.vehicle_id)
            aid = actor_id(self.vehicle)
            if aid is None:
                self.vehicle = -1
                return []
            out.append(carla.command.SetAutopilot(aid, False, tm_port))
        aid = actor_id(self.vehicle)
        if aid is None:  # the braking vehicle is gone (destroyed by the server): nothing left to brake
            self.vehicle = -1
            return out
        vx, vy, vz = velocity(self.vehicle)
        speed = math.sqrt(vx * vx + vy * vy + vz * vz)
        scale = max(0.0, speed - decel * dt) / speed if speed > 1e-6 else 0.0
        out.append(carla.command.ApplyTargetVelocity(aid, carla.Vector3D(vx * scale, vy * scale, vz * scale)))
        return out


@dataclass(frozen=True)
class Neighbour:
    """A vehicle ahead of the ego in a neighbouring lane: its scene index, the bumper gap [m] and closing
    speed [m/s] along the lane, and whether it moves right to reach the ego's lane."""

    vehicle: int
    gap: float
    closing: float
    to_right: bool


class CutIn:
    """State of the ``cut_in_ttc`` knob on one CARLA episode: the running cut-in (scene index, -1: none) and
    the events so far (the same fields as lite's, ``sim.interface.ActorEvent``)."""

    def __init__(self) -> None:
        self.vehicle = -1
        self._events: list[ActorEvent] = []
        self._offset0 = 0.0  # how far the running cut-in's car had to go into the ego's lane [m]
        self.preparing = -1  # the vehicle slowed by ``cut_in_relative_speed`` to get ready (-1: none)
        self.held: dict[int, float] = {}  # vehicles given a desired speed [m/s] by this knob

    def wanted(self, ttc: float, off: float) -> bool:
        """Whether ``step`` has anything to do: a cut-in runs, a vehicle is held, or the knob asks for one."""
        return self.vehicle >= 0 or bool(self.held) or ttc < off - 1e-9

    def step(self, tm: Any, ttc: float, off: float, now: float, neighbours: Callable[[], list[Neighbour]],
             actor: Callable[[int], Any | None], offset: Callable[[int], float | None],
             relative_speed: float = 0.0, ego_speed: float = 0.0, speed_difference_pct: float = 0.0) -> None:
        """Before a tick at episode time ``now``: follow the running cut-in (perceivable once the car has
        wandered ``CUT_IN_WANDER_M`` toward the ego's lane, over once it is within 0.5 m of the lane's centre
        line), else, when the knob asks for one (``ttc`` below ``off``), pick the car and ask ``tm`` to move it.
        ``offset(i)``: vehicle i's distance [m] from the centre line of the ego's lane (None: gone).
        ``relative_speed`` > 0 while nobody is suitable: the nearest neighbour ahead is slowed to that much
        under ``ego_speed`` [m/s]; at ``off`` every vehicle held gets ``speed_difference_pct`` back."""
        if self.vehicle >= 0:
            ev = self._events[-1]
            d = offset(self.vehicle)
            if d is None:
                self.vehicle = -1
            else:
                if ev.perceivable_s is None and self._offset0 - d >= CUT_IN_WANDER_M:
                    # R157's time-to-collision there, projected from the onset's gap at its closing speed
                    seen = (ev.gap_m - ev.closing_m_s * (now - ev.onset_s)) / ev.closing_m_s
                    self._events[-1] = replace(ev, perceivable_s=now, perceived_ttc_s=max(seen, 0.0))
                if d < 0.5:
                    self.vehicle = -1
        if ttc >= off - 1e-9:
            self._release(tm, actor, list(self.held), speed_difference_pct)
            self.preparing = -1
            return
        if self.vehicle >= 0:
            return
        near = {n.vehicle: n for n in neighbours()}
        pick = pick_cut_in(((n.vehicle, n.gap, n.closing) for n in near.values()), ttc)
        if pick is None:
            self._prepare(tm, actor, near, relative_speed, ego_speed, speed_difference_pct)
            return
        j, gap, closing = pick
        a, d0 = actor(j), offset(j)
        if a is None or d0 is None:
            return
        tm.force_lane_change(a, near[j].to_right)
        self.vehicle, self._offset0 = j, d0
        self._events.append(ActorEvent("cut_in", j, now, None, gap / closing, gap, closing))
        if j == self.preparing:  # R157's cutter keeps its speed across
            self._hold(tm, a, j, max(0.0, ego_speed - closing))
            self.preparing = -1

    def _prepare(self, tm: Any, actor: Callable[[int], Any | None], near: Mapping[int, Neighbour],
                 relative_speed: float, ego_speed: float, speed_difference_pct: float) -> None:
        j = pick_preparing({k: n.gap for k, n in near.items()}, self.preparing) if relative_speed > 0.0 else -1
        if j != self.preparing:
            self._release(tm, actor, [self.preparing] if self.preparing >= 0 else [], speed_difference_pct)
            self.preparing = -1
        a = actor(j) if j >= 0 else None
        if a is None:
            return
        self.preparing = j
        target = preparing_speed(ego_speed, relative_speed, float(a.get_speed_limit()) / 3.6)
        if abs(self.held.get(j, math.inf) - target) > 0.25:  # one call per quarter m/s, not one per tick
            self._hold(tm, a, j, target)

    def _hold(self, tm: Any, a: Any, j: int, speed: float) -> None:
        tm.set_desired_speed(a, 3.6 * speed)
        self.held[j] = speed

    def _release(self, tm: Any, actor: Callable[[int], Any | None], vehicles: list[int], pct: float) -> None:
        for j in vehicles:
            a = actor(j)
            if a is not None:
                tm.vehicle_percentage_speed_difference(a, pct)
            self.held.pop(j, None)

    def events(self) -> list[ActorEvent]:
        return list(self._events)


class TrafficBehaviour:
    """The surrounding traffic's behaviour on CARLA: each of :data:`TM_BEHAVIOUR_KNOBS` is the traffic
    manager's per-vehicle call of the same name, sent for every NPC when the knob's value changes."""

    def __init__(self) -> None:
        self.applied = dict(TM_BEHAVIOUR_KNOBS)

    def changed(self, values: Mapping[str, float]) -> list[str]:
        """The knobs whose value differs from the one last sent."""
        return [k for k in TM_BEHAVIOUR_KNOBS if float(values[k]) != self.applied[k]]

    def apply(self, tm: Any, values: Mapping[str, float], npcs: Iterable[Any]) -> list[str]:
        """Send the changed knobs to ``tm`` for each of ``npcs`` (carla.Actor); returns the knobs sent."""
        changed = self.changed(values)
        if changed:
            actors = list(npcs)
            for k in changed:
                for a in actors:
                    getattr(tm, k)(a, float(values[k]))
                self.applied[k] = float(values[k])
        return changed
