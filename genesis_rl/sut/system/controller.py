"""A following controller in the manner of CARLA's BehaviorAgent, driving on what it perceives.

Lateral: pure pursuit on its route (from the map). Longitudinal: the Intelligent Driver Model against the
nearest *perceived* vehicle in its path and against the stop line of a red (or stoppable yellow) light,
a cruise speed capped like BehaviorAgent's 'normal' profile (50 km/h) and slowed for bends, and emergency
braking when the perceived time-to-collision drops under a threshold. The lead's speed is estimated from
the perceived gap with an alpha-beta filter; a lost detection is held for a few frames, as a tracker
would. It never reads other vehicles' true states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from genesis_rl.core import ranges
from genesis_rl.sim.interface import ActorState, VehicleControl
from genesis_rl.sim.route import PolylineRoute
from genesis_rl.sut.system.protocol import Detection
from genesis_rl.world.scenes.vehicles import MAKES


@dataclass(frozen=True)
class ControllerConfig:
    """Settings with units; defaults follow BehaviorAgent's 'normal' behaviour where it has one."""

    max_speed: float = 13.9  # cruise cap [m/s] (BehaviorAgent normal: 50 km/h)
    speed_limit_margin: float = 1.4  # drive this much under the limit [m/s] (BehaviorAgent: 5 km/h)
    max_lateral_accel: float = 2.0  # slow for bends so that v^2 * curvature stays under this [m/s^2]
    time_gap: float = 1.5  # IDM safe time headway [s]
    min_gap: float = 6.0  # IDM standstill gap [m] (over the 5 m proximity rule, so clear weather is compliant)
    max_accel: float = 2.0  # IDM maximum acceleration [m/s^2]
    comfort_decel: float = 3.0  # IDM comfortable deceleration [m/s^2]
    max_decel: float = 4.0  # deceleration cap outside emergencies [m/s^2] (BehaviorAgent caps its brake at 0.5)
    ttc_emergency: float = 1.6  # full brake when the perceived time-to-collision is below this [s]
    emergency_gap: float = 2.0  # full brake when closing and the gap is below this [m]
    path_half_width: float = 1.6  # a perceived vehicle is in the path when its lateral offset is under this [m]
    perception_range: float = 60.0  # ignore detections farther along the route [m]
    track_hold_steps: int = 3  # keep a lost lead for this many steps, predicting its gap
    max_steer_deg: float = 35.0  # the vehicle's front wheel angle at steer = 1 [deg]
    throttle_accel: float = 3.0  # acceleration at full throttle (feed-forward gain) [m/s^2]
    full_brake_decel: float = 8.0  # deceleration at brake = 1 [m/s^2]

    def __post_init__(self) -> None:
        # env.system_kwargs.controller comes from a config file: each setting in its physical range
        for name, rng in CONTROLLER_RANGES.items():
            rng.check(getattr(self, name), f"system controller.{name} (env.system_kwargs.controller)")


_R = ranges.Ranged
#: the physical range of each controller setting (docs/reliability.md)
CONTROLLER_RANGES: dict[str, ranges.Ranged] = {
    "max_speed": _R(0.1, 70.0, "m/s"),
    "speed_limit_margin": _R(0.0, 20.0, "m/s"),
    "max_lateral_accel": _R(0.1, 15.0, "m/s^2"),
    "time_gap": _R(0.0, 10.0, "s"),
    "min_gap": _R(0.0, 100.0, "m"),
    "max_accel": _R(0.01, 15.0, "m/s^2"),
    "comfort_decel": _R(0.01, 15.0, "m/s^2"),
    "max_decel": _R(0.1, 30.0, "m/s^2"),
    "ttc_emergency": _R(0.0, 20.0, "s"),
    "emergency_gap": _R(0.0, 100.0, "m"),
    "path_half_width": _R(0.1, 20.0, "m"),
    "perception_range": _R(1.0, 1000.0, "m"),
    "track_hold_steps": _R(0, 1000, "steps", integer=True),
    "max_steer_deg": _R(1.0, 89.0, "deg"),
    "throttle_accel": _R(0.1, 30.0, "m/s^2"),
    "full_brake_decel": _R(0.1, 30.0, "m/s^2"),
}


@dataclass
class _LeadTrack:
    gap: float
    closing: float  # rate at which the gap shrinks [m/s]
    age: int = 0  # steps since last seen


class FollowingController:
    """Route following + IDM on perceived vehicles + traffic lights + TTC emergency braking."""

    def __init__(self, config: ControllerConfig | None = None) -> None:
        self.config = config or ControllerConfig()
        self.route: PolylineRoute | None = None
        self._track: _LeadTrack | None = None
        self._dt = 0.05
        self._signal_offset = 0.0
        self.status = "cruise"
        #: a cruise-speed cap a system sets from what it perceives (e.g. the visibility), in m/s; inf: none
        self.speed_cap = math.inf

    def reset(self, route: PolylineRoute, dt: float, signal_time_offset: float) -> None:
        self.route = route
        self._track = None
        self._dt = dt
        self._signal_offset = signal_time_offset
        self.status = "cruise"

    # -- perception -> the vehicle to follow -----------------------------------------------------------
    def _perceived_gap(self, ego: ActorState, detections: list[Detection]) -> float | None:
        """Bumper gap [m] to the nearest perceived vehicle in the route's path this frame, or None."""
        assert self.route is not None
        pos = [d.position for d in detections if d.position is not None]
        if not pos:
            return None
        p = np.asarray(pos, dtype=float)
        c, s = math.cos(ego.yaw), math.sin(ego.yaw)
        world = np.column_stack([ego.x + c * p[:, 0] - s * p[:, 1], ego.y + s * p[:, 0] + c * p[:, 1]])
        along, lateral = self.route.frame_of(world, self.config.perception_range)
        ok = np.isfinite(along) & (np.abs(lateral) < self.config.path_half_width) & (p[:, 0] > 0.0)
        if not ok.any():
            return None
        # the localised point is the nearest visible surface; the gap is measured from the ego's front bumper
        return float(max(np.min(p[ok, 0]) - 0.5 * ego.length, 0.0))

    def _update_track(self, gap: float | None) -> _LeadTrack | None:
        dt = self._dt
        tr = self._track
        if gap is None:
            if tr is None:
                return None
            tr.age += 1
            if tr.age > self.config.track_hold_steps:
                self._track = None
                return None
            tr.gap = max(tr.gap - tr.closing * dt, 0.0)
            return tr
        if tr is None or abs(gap - (tr.gap - tr.closing * dt)) > 5.0:
            self._track = _LeadTrack(gap=gap, closing=0.0)
            return self._track
        # alpha-beta filter on the gap; beta / dt gives the closing-rate correction
        pred = tr.gap - tr.closing * dt
        r = gap - pred
        tr.gap = pred + 0.5 * r
        tr.closing = tr.closing - 0.3 * r / dt
        tr.age = 0
        return tr

    # -- control ---------------------------------------------------------------------------------------
    def _idm(self, v: float, v0: float, gap: float, v_lead: float) -> float:
        c = self.config
        brake_term = v * (v - v_lead) / (2.0 * math.sqrt(c.max_accel * c.comfort_decel))
        s_star = c.min_gap + max(0.0, v * c.time_gap + brake_term)
        return c.max_accel * (1.0 - (v / max(v0, 0.1)) ** 4 - (s_star / max(gap, 0.1)) ** 2)

    def step(self, ego: ActorState, detections: list[Detection], time_s: float) -> tuple[VehicleControl, float | None]:
        """Control for the next tick and the perceived gap to the lead it follows (None: none)."""
        assert self.route is not None, "call reset() first"
        c, route, v = self.config, self.route, ego.speed
        route.update(ego.x, ego.y)

        # lateral: pure pursuit from the rear axle
        wheelbase = MAKES[ego.make].wheelbase if ego.make in MAKES else 0.6 * ego.length
        look = float(np.clip(3.0 + 0.45 * v, 4.0, 14.0))
        tx, ty = route.point_at(route.s + look)
        rx = ego.x - 0.5 * wheelbase * math.cos(ego.yaw)
        ry = ego.y - 0.5 * wheelbase * math.sin(ego.yaw)
        alpha = math.atan2(ty - ry, tx - rx) - ego.yaw
        ld = max(math.hypot(tx - rx, ty - ry), 1.0)
        delta = math.atan2(2.0 * wheelbase * math.sin(alpha), ld)
        steer = float(np.clip(-delta / math.radians(c.max_steer_deg), -1.0, 1.0))  # CARLA: + steers right

        # cruise speed: capped, under the limit, slowed for the sharpest bend within braking reach
        v0 = min(c.max_speed, route.speed_limit() - c.speed_limit_margin, self.speed_cap)
        kappa = route.curvature_ahead(max(10.0, v * v / (2 * c.comfort_decel) + 5.0))
        if kappa > 1e-3:
            v0 = min(v0, math.sqrt(c.max_lateral_accel / kappa))
        v0 = max(v0, 2.0)
        accel = self._idm(v, v0, math.inf, v)
        self.status = "cruise"

        track = self._update_track(self._perceived_gap(ego, detections))
        lead_gap = None
        if track is not None:
            lead_gap = track.gap
            v_lead = max(v - track.closing, 0.0)
            a_follow = self._idm(v, v0, track.gap, v_lead)
            if a_follow < accel:
                accel, self.status = a_follow, "follow"

        sig = route.next_signal(max_ahead=80.0)
        if sig is not None:
            ahead, light = sig
            dist = ahead - 0.5 * ego.length - 1.0
            state = route.signal_state(light, time_s + self._signal_offset)
            can_stop = dist > v * v / (2.0 * c.comfort_decel)
            if dist > -0.5 and (state == "red" or (state == "yellow" and can_stop)):
                s_star = 0.5 + v * c.time_gap * 0.5 + v * v / (2.0 * math.sqrt(c.max_accel * c.comfort_decel))
                a_light = c.max_accel * (1.0 - (v / v0) ** 4 - (s_star / max(dist, 0.1)) ** 2)
                if a_light < accel:
                    accel, self.status = a_light, "red_light"

        accel = max(accel, -c.max_decel)
        if track is not None and track.closing > 0.1:
            ttc = track.gap / track.closing
            if ttc < c.ttc_emergency or track.gap < c.emergency_gap:
                accel, self.status = -c.full_brake_decel, "emergency"

        if v < 0.3 and accel <= 0.0:
            return VehicleControl(0.0, 1.0, steer), lead_gap  # hold still
        if accel >= -0.3:
            throttle = float(np.clip((accel + 0.3) / c.throttle_accel, 0.0, 1.0))
            return VehicleControl(throttle, 0.0, steer), lead_gap
        brake = float(np.clip(-accel / c.full_brake_decel, 0.0, 1.0))
        return VehicleControl(0.0, brake, steer), lead_gap
