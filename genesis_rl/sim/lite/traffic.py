"""Traffic of the lite backend: every vehicle a kinematic bicycle, NPCs on an autopilot, all vectorised.

Autopilot (per NPC, as numpy arrays over all vehicles): pure-pursuit lane keeping along its lane and the
successor it picked at the last junction; IDM car following against the nearest vehicle in its predicted
corridor and against red or yellow lights at its lane's stop line; seeded stochastic behaviour: the target
speed wanders (an Ornstein-Uhlenbeck process) and now and then a vehicle brakes to a stop, waits and moves
on. The ego is driven by its caller's throttle/brake/steer. Colliding vehicles are put back to their
pre-impact pose and stopped, never passing through each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from genesis_rl.sim.interface import ActorEvent, Collision, LeadInfo, VehicleControl
from genesis_rl.sim.lite.collisions import colliding_pairs
from genesis_rl.sim.lite.maps.lane_graph import DS, RoadMap
from genesis_rl.world.actor_knobs import CUT_IN_WANDER_M, pick_cut_in, pick_preparing, preparing_speed
from genesis_rl.world.scenes.vehicles import MAKES

MAX_STEER = np.radians(35.0)  # front wheel angle at steer = 1 [rad]
MAX_BRAKE = 8.0  # deceleration at brake = 1 [m/s^2]
LEAD_RANGE = 80.0  # how far ahead a leader is looked for [m]
BRAKE_LIGHT_DECEL = 0.5  # brake lights are lit above this deceleration [m/s^2]
GREEN, YELLOW, RED = 0, 1, 2


@dataclass(frozen=True)
class ScriptedMotion:
    """A vehicle's motion given from outside: its pose and speed after every step (row k: after step k + 1,
    so row 0 is the pose one ``dt`` into the episode) and whether its brake lights are lit. A scripted vehicle
    still collides (contacts are reported as for any vehicle), but its pose after a step is always the
    script's: it moves as recorded, whatever the ego does. ``z`` and ``pitch`` (nose up), when given, are its
    height and pitch as recorded; else they come from its lane, as for any vehicle (a script does not follow
    lite's lanes, so after a lane change or a junction they can be another lane's)."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    braking: np.ndarray
    z: np.ndarray | None = None
    pitch: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.x)


@dataclass(frozen=True)
class AutopilotParams:
    """Per-vehicle autopilot settings (catalog fields; units in the names' comments)."""

    target_speed: float  # desired speed [m/s]
    time_gap: float  # IDM safe time headway [s]
    min_gap: float  # IDM standstill gap [m]
    max_accel: float  # IDM maximum acceleration [m/s^2]
    comfort_decel: float  # IDM comfortable deceleration [m/s^2]
    stop_rate: float  # spontaneous stops per minute
    speed_noise: float  # std of the target speed's random walk [m/s]


class Traffic:
    """State of all vehicles (index 0 is the ego) and one fixed-step update."""

    def __init__(
        self,
        road_map: RoadMap,
        makes: list[str],
        lanes: list[int],
        s: list[float],
        speeds: list[float],
        params: list[AutopilotParams | None],
        next_lanes: list[int],
        rng: np.random.Generator,
        dt: float,
    ) -> None:
        self.map = road_map
        self.rng = rng
        self.dt = dt
        n = len(makes)
        self.n = n
        self.makes = makes
        m = [MAKES[k] for k in makes]
        self.length = np.array([k.length for k in m])
        self.width = np.array([k.width for k in m])
        self.height = np.array([k.height for k in m])
        self.wheelbase = np.array([k.wheelbase for k in m])
        self.ego_max_accel = m[0].max_accel
        self.ego_max_speed = m[0].max_speed
        self.lane = np.array(lanes, dtype=np.int64)
        self.s = np.array(s, dtype=np.float64)
        self.next_lane = np.array(next_lanes, dtype=np.int64)
        idx = road_map.point_index(self.lane, self.s)
        self.x = road_map.points[idx, 0].copy()
        self.y = road_map.points[idx, 1].copy()
        self.yaw = road_map.headings[idx].copy()
        self.v = np.array(speeds, dtype=np.float64)
        self.accel = np.zeros(n)
        self.steer_angle = np.zeros(n)
        self.braking = np.zeros(n, bool)
        p = [q or AutopilotParams(0, 1.5, 2, 2, 3, 0, 0) for q in params]
        self.v0_base = np.array([q.target_speed for q in p], dtype=np.float64)
        self.v0 = self.v0_base.copy()
        self._v0_catalog = self.v0_base.copy()  # the scene's own target speeds (the TM knobs scale them)
        self._speed_factor = 1.0  # 1 - vehicle_percentage_speed_difference / 100
        self.ignore_lights = 0.0  # ignore_lights_percentage [%]
        #: NPCs that will run the red light at the end of their current lane (drawn as they enter it)
        self.runs_red = np.zeros(n, bool)
        self.time_gap = np.array([q.time_gap for q in p], dtype=np.float64)
        self.min_gap = np.array([q.min_gap for q in p], dtype=np.float64)
        self.a_max = np.array([q.max_accel for q in p], dtype=np.float64)
        self.b_comf = np.array([q.comfort_decel for q in p], dtype=np.float64)
        self.stop_rate = np.array([q.stop_rate for q in p], dtype=np.float64) / 60.0  # per second
        self.speed_noise = np.array([q.speed_noise for q in p], dtype=np.float64)
        self.stop_timer = np.zeros(n)  # > 0: holding a spontaneous stop [s]
        self.stop_decel = np.zeros(n)
        self.is_npc = np.ones(n, bool)
        self.is_npc[0] = False
        self.ego_control = VehicleControl()
        #: drive the ego with the NPC autopilot instead of ``ego_control`` (benchmarks of the traffic alone);
        #: set it with ``drive_ego_on_autopilot``, which also gives the ego a target speed
        self.ego_autopilot = False
        self.time = 0.0
        #: actor knob: (vehicle, deceleration [m/s^2], onset [s of episode time]); None: off
        self.forced_braking: tuple[int, float, float] | None = None
        #: actor knob: (vehicle, onset [s]): at onset it takes the ego's lane and steers into it
        self.forced_cut_in: tuple[int, float] | None = None
        #: vehicles that follow a given motion instead of their autopilot (an OpenSCENARIO trajectory replayed
        #: on lite): vehicle index -> its script; see ``ScriptedMotion``
        self.scripted: dict[int, ScriptedMotion] = {}
        self._script_row = -1  # the scripts' row the vehicles stand at (-1: before the first step)
        #: the vehicles the ego came into contact with this step, at the pose the contact test found them before
        #: they were put back (vehicle -> x, y, yaw): a trajectory replayed with the put-back pose would meet
        #: the ego a step later, or, in a slow creep, not at all
        self.ego_contact_poses: dict[int, tuple[float, float, float]] = {}
        self._episode_time = 0.0
        #: what the actor knobs made happen, oldest first (``actor_events``); a running cut-in's event is
        #: replaced once the cutter has wandered far enough to be perceived
        self._events: list[ActorEvent] = []
        self._cut_in_event = -1  # index in ``_events`` of the running cut-in's event (-1: none yet)
        self._cut_in_offset0 = 0.0  # how far the running cut-in's car had to go into the ego's lane [m]
        #: ``cut_in_relative_speed``: the speed [m/s] each vehicle a cut-in slowed is held to (none unless the knob
        #: is above 0, so episodes without it are as before); the one getting ready, -1: none
        self.cut_in_speed_caps: dict[int, float] = {}
        self._cut_in_preparing = -1
        self._contacts: set[tuple[int, int]] = set()
        sig = [ln.signal or (-1, 0) for ln in road_map.lanes]
        self._lane_sig_j = np.array([j for j, _ in sig], dtype=np.int64)
        self._lane_sig_g = np.array([g for _, g in sig], dtype=np.int64)
        # junction connectors inherit the signal group of the lane that feeds them: a vehicle on one
        # occupies its junction for that group (cross traffic waits until the junction is clear)
        self._conn_j = np.full(len(road_map.lanes), -1, dtype=np.int64)
        self._conn_g = np.zeros(len(road_map.lanes), dtype=np.int64)
        for ln in road_map.lanes:
            if ln.signal is not None:
                for c in ln.successors:
                    if road_map.lanes[c].junction >= 0:
                        self._conn_j[c], self._conn_g[c] = ln.signal

    def _signal_phases(self, t: float) -> np.ndarray:
        """(junctions, 2) phase codes of both signal groups of every junction at time ``t``."""
        tm = self.map.timing
        half = tm.green + tm.yellow + tm.all_red
        u = np.mod(t + self.map.signal_offsets[:, None] + np.array([0.0, half]), tm.cycle)
        return np.where(u < tm.green, GREEN, np.where(u < tm.green + tm.yellow, YELLOW, RED))

    # -- queries ---------------------------------------------------------------------------------------
    def z_pitch(self) -> tuple[np.ndarray, np.ndarray]:
        idx = self.map.point_index(self.lane, self.s)
        z, pitch = self.map.points[idx, 2], self.map.slopes[idx]
        if self._script_row >= 0:
            for i, m in self.scripted.items():
                if m.z is not None and m.pitch is not None:
                    k = min(self._script_row, len(m) - 1)
                    z[i], pitch[i] = m.z[k], m.pitch[k]
        return z, pitch

    def _frames(self) -> tuple[np.ndarray, np.ndarray]:
        """Longitudinal and lateral offsets of every vehicle j in every vehicle i's frame (i rows)."""
        dx = self.x[None, :] - self.x[:, None]
        dy = self.y[None, :] - self.y[:, None]
        c, s = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        return dx * c + dy * s, -dx * s + dy * c

    def _leaders(self, curvature: np.ndarray, bodies: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For every vehicle: index of the nearest vehicle in its predicted corridor, the bumper gap and
        that vehicle's speed along the follower's heading (gap = inf when none). ``bodies``: measure the other
        vehicle by its turned body, not as if it drove parallel, so that a car standing at an angle with a
        corner in the corridor (a cut-in stopped half across) is ahead; the NPCs' autopilot keeps the
        parallel test it was tuned with."""
        lon, lat = self._frames()
        expected = 0.5 * curvature[:, None] * lon**2
        if bodies:
            turn = self.yaw[None, :] - self.yaw[:, None]
            c, s = np.abs(np.cos(turn)), np.abs(np.sin(turn))
            half_lat = 0.5 * (self.length[None, :] * s + self.width[None, :] * c)
            half_lon = 0.5 * (self.length[None, :] * c + self.width[None, :] * s)
        else:
            half_lat, half_lon = 0.5 * self.width[None, :], 0.5 * self.length[None, :]
        half = 0.5 * self.width[:, None] + half_lat + 0.2
        same_way = np.cos(self.yaw[None, :] - self.yaw[:, None]) > -0.3
        gap = lon - 0.5 * self.length[:, None] - half_lon
        cand = (lon > 0) & (lon < LEAD_RANGE) & (np.abs(lat - expected) < half) & same_way
        np.fill_diagonal(cand, False)
        gap = np.where(cand, gap, np.inf)
        j = np.argmin(gap, axis=1)
        g = gap[np.arange(self.n), j]
        vj = self.v[j] * np.cos(self.yaw[j] - self.yaw)
        return j, g, vj

    def lead(self) -> LeadInfo | None:
        """The ego's leader by the corridor test the NPCs use (ego curvature from its steering), each vehicle
        measured by its turned body (``_leaders(bodies=True)``)."""
        curv = np.tan(self.steer_angle) / self.wheelbase
        j, g, _ = self._leaders(curv, bodies=True)
        if not np.isfinite(g[0]):
            return None
        return LeadInfo(int(j[0]), float(max(g[0], 0.0)), float(self.v[j[0]]))

    def lead_in_lane(self) -> LeadInfo | None:
        """The ego's leader for the ``lead_decel`` knob: the corridor leader (``lead``) when it drives in the
        ego's lane or the lane after it, else the nearest vehicle ahead along those two lanes. The corridor
        alone bends with the ego's steering, which is straight before the first tick: on a bend it runs
        through the next lane and would brake a neighbour while the car in front drives on."""
        corridor = self.lead()
        ego_lanes = (int(self.lane[0]), int(self.next_lane[0]))
        if corridor is not None and int(self.lane[corridor.vehicle_id]) in ego_lanes:
            return corridor
        length = float(self.map.length[ego_lanes[0]])
        best: tuple[float, int] | None = None
        for j in range(1, self.n):
            lane = int(self.lane[j])
            if lane == ego_lanes[0] and self.s[j] > self.s[0]:
                ahead = float(self.s[j] - self.s[0])
            elif lane == ego_lanes[1] and lane != ego_lanes[0]:
                ahead = length - float(self.s[0]) + float(self.s[j])
            else:
                continue
            gap = ahead - 0.5 * float(self.length[0] + self.length[j])
            if gap < LEAD_RANGE and (best is None or gap < best[0]):
                best = (gap, j)
        if best is None:
            return None
        return LeadInfo(best[1], max(best[0], 0.0), float(self.v[best[1]]))

    # -- update ----------------------------------------------------------------------------------------
    def _lookahead_points(self, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = self.map
        s_t = self.s + dist
        lane = self.lane.copy()
        over = s_t > m.length[lane]
        s_t = np.where(over, s_t - m.length[lane], s_t)
        lane = np.where(over, self.next_lane, lane)
        idx = m.point_index(lane, s_t)  # clipped: a second spill is rare and harmless (target at lane end)
        return m.points[idx, 0], m.points[idx, 1]

    def _autopilot(self) -> tuple[np.ndarray, np.ndarray]:
        """Acceleration [m/s^2] and wheel angle [rad] of every vehicle (ego rows are overwritten)."""
        m, dt = self.map, self.dt
        # target speed wanders, spontaneous stops start and end
        self.v0 += -0.05 * (self.v0 - self.v0_base) * dt + self.speed_noise * np.sqrt(dt) * self.rng.normal(size=self.n)
        self.v0 = np.clip(self.v0, 0.5 * self.v0_base, 1.3 * self.v0_base + 0.1)
        start = (self.stop_timer <= 0) & (self.rng.random(self.n) < self.stop_rate * dt) & self.is_npc
        durations = self.rng.uniform(2.0, 6.0, self.n)
        decels = self.rng.uniform(2.5, 6.5, self.n)
        self.stop_timer = np.where(start, durations + self.v / decels, self.stop_timer)
        self.stop_decel = np.where(start, decels, self.stop_decel)
        self.stop_timer = np.maximum(self.stop_timer - dt, 0.0)

        # lane keeping: pure pursuit on the rear axle
        look = np.clip(3.0 + 0.45 * self.v, 4.0, 14.0)
        tx, ty = self._lookahead_points(look)
        rear_x = self.x - 0.5 * self.wheelbase * np.cos(self.yaw)
        rear_y = self.y - 0.5 * self.wheelbase * np.sin(self.yaw)
        alpha = np.arctan2(ty - rear_y, tx - rear_x) - self.yaw
        ld = np.maximum(np.hypot(tx - rear_x, ty - rear_y), 1.0)
        delta = np.clip(np.arctan2(2.0 * self.wheelbase * np.sin(alpha), ld), -MAX_STEER, MAX_STEER)

        # car following (IDM) against the corridor leader and the stop line of a red/yellow light
        _, gap, v_lead = self._leaders(np.tan(delta) / self.wheelbase)
        # stop lines: lanes that end at a red light, or a yellow one the vehicle can still stop for
        sig_j = self._lane_sig_j[self.lane]
        phase = self._signal_phases(self.time)[np.maximum(sig_j, 0), self._lane_sig_g[self.lane]]
        dist = m.length[self.lane] - self.s - 0.5 * self.length - 1.0
        can_stop = dist > self.v**2 / (2 * self.b_comf)
        # junction occupancy: (junction, group) pairs with a vehicle on one of their connectors
        occupied = np.zeros((len(m.junctions), 2), bool)
        cj = self._conn_j[self.lane]
        inside = cj >= 0
        occupied[cj[inside], self._conn_g[self.lane][inside]] = True
        cross_busy = occupied[np.maximum(sig_j, 0), 1 - self._lane_sig_g[self.lane]]
        red = (phase == RED) | ((phase == YELLOW) & can_stop) | (cross_busy & can_stop)
        must_stop = (sig_j >= 0) & self.is_npc & (dist > -0.5) & red & ~self.runs_red
        gap_light = np.where(must_stop, np.maximum(dist, 0.01), np.inf)
        use_light = gap_light < gap
        gap = np.where(use_light, gap_light, gap)
        v_lead = np.where(use_light, 0.0, v_lead)
        v0 = np.maximum(self.v0, 0.1)
        dv = self.v - v_lead
        s_star = self.min_gap + np.maximum(
            0.0, self.v * self.time_gap + self.v * dv / (2.0 * np.sqrt(self.a_max * self.b_comf))
        )
        free = 1.0 - (self.v / v0) ** 4
        interact = np.where(np.isfinite(gap), (s_star / np.maximum(gap, 0.1)) ** 2, 0.0)
        acc = self.a_max * (free - interact)
        stopping = self.stop_timer > 0
        acc = np.where(stopping, np.minimum(acc, -self.stop_decel), acc)
        return np.clip(acc, -MAX_BRAKE, self.a_max), delta

    def drive_ego_on_autopilot(self, target_speed: float = 13.9) -> None:
        """Let the NPC autopilot drive the ego at ``target_speed`` [m/s] (50 km/h by default). The ego has no
        autopilot parameters of its own (its target speed is 0, so the autopilot alone crawled at 0.1 m/s)."""
        self.ego_autopilot = True
        self.v0_base[0] = self.v0[0] = target_speed

    def set_lead_braking(self, decel: float) -> None:
        """The ``lead_decel`` actor knob: with ``decel`` > 0 the ego's current leader brakes at ``decel`` m/s^2
        from now on; later calls change the deceleration of that same vehicle (it stays the braking one even
        if the ego changes lanes); 0 releases it to its autopilot. No leader in range: nothing brakes."""
        if decel <= 0.0:
            self.forced_braking = None
            return
        if self.forced_braking is not None:
            i, _, onset = self.forced_braking
            self.forced_braking = (i, float(decel), onset)
            return
        lead = self.lead_in_lane()
        if lead is not None:
            self.forced_braking = (lead.vehicle_id, float(decel), self._episode_time)
            # its brake lights come on with the braking: a careful driver perceives it at once
            self._events.append(ActorEvent("lead_braking", lead.vehicle_id, self._episode_time, self._episode_time))

    @property
    def braking_vehicle(self) -> int:
        """The vehicle the ``lead_decel`` knob brakes (-1: none)."""
        return -1 if self.forced_braking is None else int(self.forced_braking[0])

    def set_traffic_behaviour(self, speed_difference_pct: float, ignore_lights_pct: float) -> None:
        """Two of CARLA TrafficManager's per-vehicle parameters, for every NPC alike, under their TM names:
        ``vehicle_percentage_speed_difference`` (each NPC's target speed is its own times 1 - pct/100, as TM
        scales the speed limit) and ``ignore_lights_percentage`` (the chance that an NPC runs the red light at
        the end of a lane, drawn from the episode's seed as it enters the lane). At their defaults (0, 0)
        nothing changes and nothing is drawn, so episodes without them are as before."""
        factor = 1.0 - float(speed_difference_pct) / 100.0
        if factor != self._speed_factor:
            npc = self.is_npc & ~np.isin(np.arange(self.n), list(self.scripted))
            new_base = self._v0_catalog * factor
            self.v0[npc] += new_base[npc] - self.v0_base[npc]  # keep each one's wander around its target
            self.v0_base[npc] = new_base[npc]
            self._speed_factor = factor
        self.ignore_lights = float(ignore_lights_pct)

    def set_cut_in(self, ttc: float, off: float, relative_speed: float = 0.0) -> None:
        """The ``cut_in_ttc`` actor knob: below ``off`` (its default), the nearest slower vehicle ahead in a
        neighbouring lane of the ego's starts a lane change in front of the ego once the gap it would cut
        into closes to ``ttc`` seconds at the current closing speed (within ``CUT_IN_TTC_WINDOW`` below it).
        One cut-in at a time: the next may start once the cutter is in the ego's lane. Nobody suitable:
        nothing happens (the knob asks, the traffic decides whether it can).

        ``relative_speed`` > 0 (the ``cut_in_relative_speed`` knob): while nobody is suitable, the nearest
        vehicle ahead one lane over gets ready: it slows, at most at its comfortable deceleration, to that much
        under the ego's speed (never under ``CUT_IN_SPEED_FLOOR`` of its own target speed), so its gap closes at
        R157's kind of relative speed until it reaches ``ttc``. The cutter then holds the speed it crossed at
        (R157's cutter keeps its speed) until the knob is back at ``off``, when every vehicle it held drives on
        as its autopilot wants."""
        if ttc >= off - 1e-9:
            self.cut_in_speed_caps.clear()
            self._cut_in_preparing = -1
            return
        if self.forced_cut_in is not None and not self._cut_in_done():
            return
        candidate = self._cut_in_candidate(ttc)
        if candidate is None:
            self._prepare_cut_in(relative_speed)
            return
        j, gap, closing = candidate
        self.forced_cut_in = (j, self._episode_time)
        self._cut_in_event = len(self._events)
        self._events.append(ActorEvent("cut_in", j, self._episode_time, None, gap / closing, gap, closing))
        self._cut_in_offset0 = 0.0  # set when the car starts across (``_start_cut_in``)
        if j == self._cut_in_preparing:
            self.cut_in_speed_caps[j] = float(self.v[j])
            self._cut_in_preparing = -1

    def _prepare_cut_in(self, relative_speed: float) -> None:
        """Slow the neighbour ``actor_knobs.pick_preparing`` names to ``actor_knobs.preparing_speed`` (see
        ``set_cut_in``); at 0, or with nobody ahead, the one getting ready goes."""
        gaps = {j: gap for j, gap, _ in self._beside_ahead() if j not in self.scripted}
        j = pick_preparing(gaps, self._cut_in_preparing) if relative_speed > 0.0 else -1
        if j != self._cut_in_preparing:
            self.cut_in_speed_caps.pop(self._cut_in_preparing, None)
            self._cut_in_preparing = j
        if j >= 0:
            self.cut_in_speed_caps[j] = preparing_speed(float(self.v[0]), float(relative_speed),
                                                        float(self.v0_base[j]))

    def _beside_ahead(self) -> list[tuple[int, float, float]]:
        """(vehicle, bumper gap [m], speed along the ego's heading [m/s]) of every vehicle in a neighbouring
        lane of the ego's, measured along the ego's heading (gaps of vehicles behind are negative)."""
        lane = self.map.lanes[int(self.lane[0])]
        neighbours = {lane.left, lane.right} - {-1}
        return [(j, *self._along_ego(j)) for j in range(1, self.n) if int(self.lane[j]) in neighbours]

    def _along_ego(self, j: int) -> tuple[float, float]:
        """Vehicle ``j``'s bumper gap ahead of the ego [m] and its speed [m/s], both along the ego's heading."""
        c, s = np.cos(self.yaw[0]), np.sin(self.yaw[0])
        gap = (self.x[j] - self.x[0]) * c + (self.y[j] - self.y[0]) * s - 0.5 * (self.length[0] + self.length[j])
        return float(gap), float(self.v[j] * np.cos(self.yaw[j] - self.yaw[0]))

    def _cut_in_candidate(self, ttc: float) -> tuple[int, float, float] | None:
        """(vehicle, bumper gap [m], closing speed [m/s]) of the vehicle to cut in (``actor_knobs.pick_cut_in``)."""
        if self.v[0] < 1.0:
            return None
        return pick_cut_in(((j, gap, float(self.v[0]) - speed) for j, gap, speed in self._beside_ahead()
                            if j not in self.scripted), ttc)

    def neighbour_ahead(self) -> LeadInfo | None:
        """The nearest vehicle ahead of the ego in a neighbouring lane (the ``cut_in_ttc`` candidates' lanes)."""
        ahead = [(j, gap, speed) for j, gap, speed in self._beside_ahead() if 0.0 < gap < LEAD_RANGE]
        if not ahead:
            return None
        j, gap, speed = min(ahead, key=lambda a: a[1])
        return LeadInfo(j, gap, speed)

    def _lateral_offset(self, i: int) -> float:
        """Signed distance [m] of vehicle ``i`` from the centre line of its lane (left positive)."""
        k = int(self.map.point_index(self.lane[i], self.s[i]))
        h = self.map.headings[k]
        return float(-(self.x[i] - self.map.points[k, 0]) * np.sin(h) + (self.y[i] - self.map.points[k, 1]) * np.cos(h))

    def _cut_in_done(self) -> bool:
        assert self.forced_cut_in is not None
        i = self.forced_cut_in[0]
        return bool(self.lane[i] == self.lane[0] and abs(self._lateral_offset(i)) < 0.5)

    def _running_cut_in(self) -> ActorEvent | None:
        """The event of the cut-in ``forced_cut_in`` runs (the latest cut-in: a lead braked meanwhile adds its
        own event after it)."""
        return self._events[self._cut_in_event] if self._cut_in_event >= 0 else None

    def _note_cut_in_wander(self) -> None:
        """Mark the running cut-in perceivable once the cutter has wandered ``CUT_IN_WANDER_M`` toward the
        ego's lane (R157's lateral wandering distance)."""
        ev = self._running_cut_in()
        if ev is None or ev.perceivable_s is not None or self.lane[ev.vehicle_id] != self.lane[0]:
            return
        if self._cut_in_offset0 - abs(self._lateral_offset(ev.vehicle_id)) >= CUT_IN_WANDER_M:
            self._events[self._cut_in_event] = replace(ev, perceivable_s=self._episode_time,
                                                       perceived_ttc_s=self._time_to_collision(ev.vehicle_id))

    def _time_to_collision(self, i: int) -> float:
        """The ego's time-to-collision [s] with vehicle ``i`` now: the bumper gap along the ego's heading over the
        closing speed (inf when not closing)."""
        gap, speed = self._along_ego(i)
        closing = float(self.v[0]) - speed
        return max(gap, 0.0) / closing if closing > 1e-6 else math.inf

    def actor_events(self) -> list[ActorEvent]:
        """What the actor knobs made happen so far (see :class:`~genesis_rl.sim.interface.ActorEvent`)."""
        return list(self._events)

    def _start_cut_in(self) -> None:
        """Put the cutter on the ego's lane at its longitudinal position (pure pursuit then steers it in)."""
        assert self.forced_cut_in is not None
        i, onset = self.forced_cut_in
        if self.lane[i] == self.lane[0] or self._episode_time + 1e-9 < onset:
            return
        d = (self.x[i] - self.x[0]) * np.cos(self.yaw[0]) + (self.y[i] - self.y[0]) * np.sin(self.yaw[0])
        self.lane[i], self.next_lane[i] = self.lane[0], self.next_lane[0]
        self.s[i] = self.s[0] + d
        ev = self._running_cut_in()
        if ev is not None and ev.vehicle_id == i:
            self._cut_in_offset0 = abs(self._lateral_offset(i))  # how far it has to go: about a lane's width

    def step(self, step_index: int) -> list[Collision]:
        dt = self.dt
        if self.forced_cut_in is not None:
            self._start_cut_in()
        acc, delta = self._autopilot()
        if not self.ego_autopilot:
            c = self.ego_control
            v_e = self.v[0]
            acc[0] = (
                c.throttle * self.ego_max_accel * max(0.0, 1.0 - v_e / self.ego_max_speed)
                - c.brake * MAX_BRAKE
                - 0.05
                - 0.0004 * v_e * v_e
            )
            delta[0] = c.steer * MAX_STEER * -1.0  # CARLA: positive steer turns right (clockwise)
        for i, cap in self.cut_in_speed_caps.items():  # toward the held speed within 1 s, braking comfortably
            acc[i] = min(acc[i], max(-self.b_comf[i], cap - self.v[i]))
        if self.forced_braking is not None:
            i, decel, onset = self.forced_braking
            # brake for the part of this step after onset, so the profile does not depend on dt
            share = min(1.0, max(0.0, (self._episode_time + dt - onset) / dt))
            if share > 0.0:
                acc[i] = -decel * share
        self.braking = acc < -BRAKE_LIGHT_DECEL
        self.accel = acc
        self.steer_angle = delta

        prev = (self.x.copy(), self.y.copy(), self.yaw.copy())
        v_before = self.v.copy()
        v_new = np.maximum(self.v + acc * dt, 0.0)
        v_mid = 0.5 * (self.v + v_new)
        beta = np.arctan(0.5 * np.tan(delta))  # slip angle at the centre (lr = wheelbase / 2)
        self.x = self.x + v_mid * np.cos(self.yaw + beta) * dt
        self.y = self.y + v_mid * np.sin(self.yaw + beta) * dt
        self.yaw = self.yaw + v_mid / (0.5 * self.wheelbase) * np.sin(beta) * dt
        self.v = v_new
        scripted = self._apply_scripts(step_index)

        pairs = colliding_pairs(self.x, self.y, self.yaw, self.length, self.width)
        # a collision is reported once, when contact begins; vehicles in contact stay stopped
        collisions = [
            Collision(step_index, i, j, float(v_before[i]), float(v_before[j]),
                      float(abs(v_before[i] - v_before[j] * np.cos(self.yaw[j] - self.yaw[i]))))
            for i, j in pairs
            if (i, j) not in self._contacts
        ]
        self.ego_contact_poses = {j: (float(self.x[j]), float(self.y[j]), float(self.yaw[j]))
                                  for i, j in pairs if i == 0 and (i, j) not in self._contacts}
        self._contacts = set(pairs)
        if pairs:
            hit = np.setdiff1d(np.unique(np.array(pairs).ravel()), scripted)  # a script already holds its pose
            self.x[hit], self.y[hit], self.yaw[hit] = prev[0][hit], prev[1][hit], prev[2][hit]
            self.v[hit] = 0.0
        self._advance_lanes()
        self.time += dt
        self._episode_time += dt
        if self.forced_cut_in is not None:
            self._note_cut_in_wander()
        return collisions

    def _apply_scripts(self, step_index: int) -> np.ndarray:
        """Put every scripted vehicle at its script's pose after this step (held at the script's last row once
        it ends); returns their indices."""
        self._script_row = step_index
        for i, m in self.scripted.items():
            k = min(step_index, len(m) - 1)
            self.x[i], self.y[i], self.yaw[i], self.v[i] = m.x[k], m.y[k], m.yaw[k], m.speed[k]
            self.braking[i] = bool(m.braking[k])
        return np.array(sorted(self.scripted), dtype=np.int64)

    def _advance_lanes(self) -> None:
        m = self.map
        idx = m.point_index(self.lane, self.s)
        hx, hy = np.cos(m.headings[idx]), np.sin(m.headings[idx])
        # progress along the lane = projection of the position on the lane tangent
        ds = (self.x - m.points[idx, 0]) * hx + (self.y - m.points[idx, 1]) * hy
        self.s = np.maximum(self.s + ds, 0.0)
        for i in np.flatnonzero(self.s > m.length[self.lane]):
            self.s[i] -= m.length[self.lane[i]]
            self.lane[i] = self.next_lane[i]
            succ = m.lanes[self.lane[i]].successors
            self.next_lane[i] = succ[int(self.rng.integers(len(succ)))]
            # ignore_lights_percentage: drawn only while it is on, so the default draws nothing
            self.runs_red[i] = bool(self.ignore_lights > 0.0 and self.is_npc[i]
                                    and self.rng.random() < self.ignore_lights / 100.0)
        # the ego may leave its lane (its driver is the system under test): re-anchor it when it does
        i0 = int(m.point_index(self.lane[0], self.s[0]))
        if (self.x[0] - m.points[i0, 0]) ** 2 + (self.y[0] - m.points[i0, 1]) ** 2 > 4.0**2:
            k = m.nearest_lane_point(self.x[0], self.y[0], self.yaw[0])
            lane = int(m.point_lane[k])
            self.lane[0], self.s[0] = lane, (k - m.offset[lane]) * DS
            succ = m.lanes[lane].successors
            self.next_lane[0] = succ[int(self.rng.integers(len(succ)))]
