"""The actor knobs on a CARLA server: ``lead_decel`` by per-actor control (issue 32).

CARLA's TrafficManager has no "brake now at X m/s^2" call, so the braking lead leaves the traffic manager
(``SetAutopilot(False)``) and is given each tick a target velocity that is its current one shortened by
``lead_decel * dt``, along its own direction (``ApplyTargetVelocity``, applied before the physics step).
When the knob returns to 0 the vehicle rejoins the traffic manager. The lead is the one ahead of the ego when
the knob rises (``CarlaSimulation.lead``), as on lite; it stays the braking vehicle until the knob is 0.

Physics then acts on the commanded velocity (tyre friction, slopes), so the realised deceleration on a
server can differ from the demand by what one tick of physics adds; on lite it is exact.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from genesis_rl.sim.interface import LeadInfo

#: the actor knobs a CARLA simulation realises
CARLA_ACTOR_KNOBS: tuple[str, ...] = ("lead_decel",)


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
