"""The lite backend: a Simulation over :class:`Traffic` with the Panda3D camera (created lazily)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.state_copy import copy_state
from genesis_rl.sim.interface import (
    ActorEvent,
    ActorState,
    Backend,
    CameraConfig,
    LeadInfo,
    SensorFrame,
    Simulation,
    SnapshotUnsupported,
    TickResult,
    VehicleControl,
)
from genesis_rl.sim.lite.maps import MAP_NAMES, load_map
from genesis_rl.sim.lite.traffic import AutopilotParams, Traffic
from genesis_rl.world.knobs import KNOBS, Weather, frame_hooks
from genesis_rl.world.scenes.catalog import Scene


@dataclass(frozen=True)
class LiteSnapshot:
    """A lite world at one tick: the traffic (every vehicle, its controller state and random generator), the
    tick count and the weather of the next frame. The renderer holds no state of its own that a frame depends
    on (a frame is a function of the poses, the weather, the time and the (world seed, step) noise draw)."""

    scene: tuple[str, int]  # the scene's map and seed: a snapshot is restored into a simulation of that scene
    world_seed: int
    step: int
    traffic: Traffic
    weather: Weather


class LiteSimulation(Simulation):
    """One episode on a lite map. All randomness comes from ``seed`` (NPC behaviour, sensor noise)."""

    def __init__(self, backend: LiteBackend, scene: Scene, seed: int, weather: Weather,
                 camera: CameraConfig, render: bool) -> None:
        self._backend = backend
        self.scene = scene
        self.map = load_map(scene.map)
        self.camera = camera
        self._weather = weather
        self._step = 0
        self.seed = int(seed)
        rng = np.random.default_rng(np.random.SeedSequence([scene.seed, self.seed]))
        vs = scene.vehicles
        self.traffic = Traffic(
            self.map,
            [v.make for v in vs],
            [v.lane for v in vs],
            [v.s for v in vs],
            [v.speed for v in vs],
            [AutopilotParams(**v.autopilot) if v.autopilot else None for v in vs],
            [v.next_lane for v in vs],
            rng,
            self.dt,
        )
        self.traffic.time = scene.signal_offset
        self._renderer = backend.acquire_renderer(self.map.name, camera) if render else None
        if self._renderer is not None:
            self._renderer.set_episode_seed(self.seed)
            self._renderer.set_vehicles([(i, v.make, v.color) for i, v in enumerate(vs)])
        self._destroyed = False

    def set_weather(self, weather: Weather) -> None:
        """Every knob for the next frame; actor knobs (``lite = 'traffic'``) act on the traffic from the next tick."""
        super().set_weather(weather)
        self.traffic.set_lead_braking(float(weather["lead_decel"]))
        self.traffic.set_cut_in(float(weather["cut_in_ttc"]), KNOBS["cut_in_ttc"].default,
                                float(weather["cut_in_relative_speed"]))
        self.traffic.set_traffic_behaviour(float(weather["vehicle_percentage_speed_difference"]),
                                           float(weather["ignore_lights_percentage"]))

    def actor_events(self) -> list[ActorEvent]:
        return self.traffic.actor_events()

    def neighbour_ahead(self) -> LeadInfo | None:
        return self.traffic.neighbour_ahead()

    def apply_ego_control(self, control: VehicleControl) -> None:
        self.traffic.ego_control = control

    snapshot_unsupported = None

    def snapshot(self) -> LiteSnapshot:
        return LiteSnapshot((self.scene.map, self.scene.seed), self.seed, self._step,
                            copy_state(self.traffic), self._weather)

    def restore(self, state: object) -> None:
        if not isinstance(state, LiteSnapshot):
            raise SnapshotUnsupported(f"a lite simulation restores a LiteSnapshot, not {type(state).__name__}")
        if state.scene != (self.scene.map, self.scene.seed):
            raise SnapshotUnsupported(f"snapshot of scene {state.scene} restored into scene "
                                      f"{(self.scene.map, self.scene.seed)}: a snapshot returns to its own scene")
        self.traffic = copy_state(state.traffic)  # the snapshot stays reusable; the map is shared (SNAPSHOT_SHARED)
        self._step, self._weather, self.seed = state.step, state.weather, state.world_seed
        if self._renderer is not None:
            self._renderer.set_episode_seed(self.seed)

    def tick(self) -> TickResult:
        collisions = self.traffic.step(self._step)
        self._step += 1
        return TickResult(self._step, self._step * self.dt, collisions)

    def poses(self) -> np.ndarray:
        t = self.traffic
        z, pitch = t.z_pitch()
        return np.column_stack([t.x, t.y, z, t.yaw, pitch])

    def observe(self) -> SensorFrame:
        if self._renderer is None:
            raise RuntimeError("this simulation was created with render=False")
        t = self.traffic
        dims = np.column_stack([t.length, t.width, t.height])
        rgb, depth, labels, boxes = self._renderer.render(
            self.poses(), t.braking, dims, self._weather, t.time, self._step
        )
        for knob in frame_hooks():  # knobs declared with their own lite effect (knobs.register_knob)
            value = float(self._weather[knob.name])
            if value != knob.default:
                rgb = knob.frame_hook(rgb, depth, value)  # type: ignore[misc]
        return SensorFrame(self._step, rgb, depth, boxes, labels)

    def actors(self) -> list[ActorState]:
        t = self.traffic
        p = self.poses()
        out = []
        for i, v in enumerate(self.scene.vehicles):
            x, y, z, yaw, pitch = map(float, p[i])  # poses(): one row of x, y, z, yaw, pitch per vehicle
            out.append(ActorState(i, v.role, v.make, x, y, z, yaw, pitch, float(t.v[i]), float(t.length[i]),
                                  float(t.width[i]), float(t.height[i])))
        return out

    def lead(self) -> LeadInfo | None:
        return self.traffic.lead()

    def destroy(self) -> None:
        if not self._destroyed and self._renderer is not None:
            self._renderer.clear_vehicles()
            self._backend.release_renderer(self._renderer)
        self._destroyed = True


class LiteBackend(Backend):
    """Pools renderers per (map, camera) so that episodes reuse the built scenery (seconds to build); a
    renderer serves one live simulation at a time, so simulations open side by side never share one."""

    name = "lite"
    catalog_kind = "lite"
    #: Traffic.set_lead_braking, .set_cut_in, .set_traffic_behaviour
    actor_knobs = ("lead_decel", "cut_in_ttc", "vehicle_percentage_speed_difference", "ignore_lights_percentage",
                   "cut_in_relative_speed")
    #: Bumped whenever a change to the renderer changes pixels (records keep it: replay says when it
    #: differs, since the detector then sees slightly different frames). 2: tiled, two-level static scene.
    #: 3: roads and markings on simplified polylines, coarser ground in far blocks (<= 0.14 % of pixels).
    #: 4: opaque geometry drawn in scene-graph order, not Panda3D's state order, which hung on memory
    #: addresses and so on the process's history (surfaces at one depth; 15 of 15,360 steps detected otherwise).
    #: 5: darker, fuller contact shadows, lighter rear windows; the camera's vignetting and auto-exposure
    #: (docs/realism_render.md).
    render_version = 5

    def __init__(self) -> None:
        self._renderers: dict[tuple, list] = {}
        self._in_use: set[int] = set()

    def map_names(self) -> list[str]:
        return list(MAP_NAMES)

    def acquire_renderer(self, map_name: str, camera: CameraConfig):  # noqa: ANN201
        from genesis_rl.sim.lite.render.panda_renderer import LiteRenderer  # local: start-up cost (panda3d, cv2)

        pool = self._renderers.setdefault((map_name, camera), [])
        for r in pool:
            if id(r) not in self._in_use:
                break
        else:
            r = LiteRenderer(load_map(map_name), camera, seed=0)
            pool.append(r)
        self._in_use.add(id(r))
        return r

    def release_renderer(self, renderer: object) -> None:
        self._in_use.discard(id(renderer))

    def create_simulation(self, scene: Scene, *, seed: int, weather: Weather | None = None,
                          camera: CameraConfig | None = None, render: bool = True) -> LiteSimulation:
        if scene.map not in MAP_NAMES:
            raise UserInputError(f"scene map '{scene.map}' is not a lite map; allowed: {', '.join(MAP_NAMES)}")
        return LiteSimulation(self, scene, seed, weather or Weather.default(), camera or CameraConfig(), render)

    def close(self) -> None:
        for pool in self._renderers.values():
            for r in pool:
                r.close()
        self._renderers.clear()
        self._in_use.clear()
