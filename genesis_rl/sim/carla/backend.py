"""The CARLA backend: the simulator interface on a CARLA 0.9.16 server.

One :class:`CarlaBackend` is one client connection (and its traffic manager port); each episode is a
:class:`CarlaSimulation` that loads the scene's map if needed, switches the server to synchronous mode with a
0.05 s fixed step (so the server waits for our ticks and sensor frames match ticks), seeds the traffic manager
and puts it in synchronous mode (deterministic NPCs), spawns the scene and the ego's sensors, and on
``destroy`` removes everything it spawned and restores the server's previous settings. ``destroy`` runs on
any error during setup and, through the context manager, on any error during the episode: a client that dies
with the server in synchronous mode would otherwise leave it frozen, waiting for ticks.
"""

from __future__ import annotations

import math
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.carla._carla import require_carla
from genesis_rl.sim.carla.actor_control import CARLA_ACTOR_KNOBS, CutIn, LeadBraking, Neighbour, TrafficBehaviour
from genesis_rl.sim.carla.connection import (
    CarlaServerLost,
    check_numbers,
    connect,
    guarded,
    is_connection_error,
    start_hint,
)
from genesis_rl.sim.carla.contacts import ContactTracker
from genesis_rl.sim.carla.frames import camera_mount, pose_from_carla
from genesis_rl.sim.carla.identity import opendrive_digest, short
from genesis_rl.sim.carla.lead import PATH_LENGTH, lane_path, lead_on_path, path_offset
from genesis_rl.sim.carla.ports import (
    TrafficManagerPortBusy,
    busy_message,
    default_tm_port,
    ensure_free,
    free_port,
    is_bind_error,
)
from genesis_rl.sim.carla.projection import ground_truth_boxes
from genesis_rl.sim.carla.sensors import FrameQueue, bgra_to_rgb, decode_depth
from genesis_rl.sim.carla.spawn import SpawnSpec, initial_velocity, plan_scene, spawn_commands
from genesis_rl.sim.carla.weather import to_carla
from genesis_rl.sim.interface import (
    ActorEvent,
    ActorState,
    Backend,
    CameraConfig,
    Collision,
    ConnectionSettings,
    LeadInfo,
    SensorFrame,
    Simulation,
    TickResult,
    VehicleControl,
)
from genesis_rl.sim.watchdog import SimulatorHung, Watchdog, deadline_for
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.scenes.catalog import Scene
from genesis_rl.world.scenes.vehicles import MAKES

T = TypeVar("T")

DEFAULT_HOST = "localhost"
DEFAULT_PORT = 2000
DEFAULT_TIMEOUT = 10.0  # [s] per client call (a tick with 30 vehicles and two cameras takes well under 1 s)
LOAD_TIMEOUT = 120.0  # [s] loading a town takes tens of seconds on a cold server
#: traffic-manager ports of this process whose traffic manager was abandoned with a lost server: it still
#: listens there (shutting it down would call the dead server from a noexcept destructor: the process aborts)
_ABANDONED_TM_PORTS: set[int] = set()
#: traffic-manager ports this process has open: another connection of this process (a campaign's oracle env)
#: gets the same traffic manager back from the client, so the port is not free and need not be
_OPEN_TM_PORTS: set[int] = set()
#: live episodes of this process per server (host, port): a server one of them holds in synchronous mode is
#: neither orphaned nor driven by another run
_OUR_EPISODES: dict[tuple[str, int], int] = {}
MIN_EXTENT = 0.05  # [m] a half extent this small is no bounding box (see CarlaSimulation._box)
VELOCITY_HISTORY = 32  # [frames] snapshots' velocities kept for collision events that arrive late


#: The RGB camera adapts its exposure at once instead of over seconds (CARLA's default, 'histogram' with speeds
#: of 3 and 1 EV/s): the detector sees a settled image right after a spawn or a sudden change of the knobs,
#: as a run replayed from any step would.
EXPOSURE_SPEED = 100.0  # [EV/s]
CAMERA_ATTRIBUTES = {
    "sensor.camera.rgb": {"exposure_mode": "histogram", "exposure_speed_up": f"{EXPOSURE_SPEED:g}",
                          "exposure_speed_down": f"{EXPOSURE_SPEED:g}"},
}


#: [s] how long a server found in synchronous mode is watched for another client's tick before it is taken
#: for orphaned (a live run ticks many times a second; one that pauses longer between episodes is missed)
ORPHAN_WATCH_S = 3.0


class ServerInUse(UserInputError):
    """Another live client drives this server (it ticks it in synchronous mode): each run needs its own."""


def check_not_driven(world: Any, where: str, watch_s: float = ORPHAN_WATCH_S) -> None:
    """A server in synchronous mode advances only when a client ticks it: wait ``watch_s`` for a tick that
    is not ours (``world.wait_for_tick``). One that comes means a live run drives the server, which this run
    would tick under it, reseed its traffic manager and, at close, put into asynchronous mode: refuse."""
    t0 = time.monotonic()
    try:
        snapshot = world.wait_for_tick(watch_s)
    except RuntimeError as err:
        if is_connection_error(err) and "time" in str(err).lower():
            return  # no tick within watch_s: nobody drives it, the server was orphaned
        raise
    raise ServerInUse(
        f"CARLA server {where} is in synchronous mode and another client ticks it (frame {snapshot.frame} came "
        f"{time.monotonic() - t0:.1f} s into a {watch_s:g} s watch): another run drives this server. Give this run "
        "a server of its own (--carla-port, --carla-servers), or stop the other run")


def original_settings(settings: Any, where: str) -> Any:
    """The settings to restore after an episode. A server found in synchronous mode (and not ticked by anyone:
    :func:`check_not_driven`) was left so by a client that died: restoring that would freeze it again, so it
    is restored to asynchronous mode, with a warning."""
    if settings.synchronous_mode:
        warnings.warn(f"CARLA server {where} was in synchronous mode (left by a killed client?); it is put back "
                      "in asynchronous mode after the run", RuntimeWarning, stacklevel=3)
        settings.synchronous_mode = False
        settings.fixed_delta_seconds = None
    return settings


def _tm_setup(tm: Any, seed: int) -> None:
    """The traffic manager of an episode: synchronous (deterministic NPCs), seeded, full physics for every
    NPC (the same dynamics near and far), no respawning of dormant vehicles."""
    tm.set_synchronous_mode(True)
    tm.set_random_device_seed(seed)
    tm.set_hybrid_physics_mode(False)
    tm.set_respawn_dormant_vehicles(False)


def map_basename(path: str) -> str:
    """'/Game/Carla/Maps/Town05' or 'Carla/Maps/Town05' -> 'Town05'."""
    return path.rstrip("/").rsplit("/", 1)[-1]


def episode_seed(scene: Scene, seed: int) -> int:
    """The traffic manager's seed: both the scene's and the episode's seed matter, as in the lite backend."""
    return int(np.random.SeedSequence([scene.seed, int(seed)]).generate_state(1)[0] & 0x7FFFFFFF)


class CarlaBackend(Backend):
    """A connection to a CARLA server at ``host:port``; a dead or slow server fails here, with a message
    naming host:port and how to start one (:class:`~genesis_rl.sim.carla.connection.CarlaConnectionError`)."""

    name = "carla"
    catalog_kind = "carla"
    actor_knobs = CARLA_ACTOR_KNOBS  # actor_control.py
    needs_catalog = True  # scenes are generated on a server, once: genesis-rl scenes --backend carla

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, timeout: float = DEFAULT_TIMEOUT,
                 tm_port: int | None = None, map: str | None = None, load_timeout: float = LOAD_TIMEOUT) -> None:
        self.host, self.port = str(host), int(port)
        self.timeout, self.load_timeout = float(timeout), float(load_timeout)
        check_numbers(self.port, self.timeout, tm_port)  # --carla-tm-port 70000, --carla-timeout inf
        self.watchdog = Watchdog(f"CARLA server {self.host}:{self.port}")
        self.client = connect(self.host, self.port, self.timeout)
        self.tm_port = default_tm_port(self.port, tm_port)  # one per run: two runs never share a port
        self._live: set[CarlaSimulation] = set()
        self._map_cache: tuple[int, Any] | None = None
        self._digest_cache: tuple[int, str] | None = None
        self._planner: tuple[tuple[int, str], Any, dict[int, float]] | None = None
        self._tm: Any = None
        if map is not None:
            self.load_map(map)

    @classmethod
    def from_settings(cls, settings: ConnectionSettings) -> CarlaBackend:
        return cls(settings.host, settings.port, settings.timeout, settings.tm_port)

    def call(self, what: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run a client call under the watchdog (:mod:`genesis_rl.sim.watchdog`); a lost or hung server becomes
        :class:`CarlaServerLost` naming ``what``."""
        return self.call_within(what, deadline_for(self.timeout), fn, *args, **kwargs)

    def call_within(self, what: str, seconds: float, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """:meth:`call` with the watchdog's deadline ``seconds`` (loading a map takes longer than a tick)."""
        try:
            return self.watchdog.call(what, seconds, guarded, self.host, self.port, what, fn, *args, **kwargs)
        except SimulatorHung as err:
            self._give_up()
            raise CarlaServerLost(f"{err}. Check the server's log and restart it if it is stuck; "
                                  + start_hint(self.host, self.port)) from err

    @property
    def lost(self) -> bool:
        """The watchdog gave this connection up: nothing more is asked of its server."""
        return self.watchdog.lost is not None

    def _give_up(self) -> None:
        """Keep the client and its traffic manager alive for good (a thread is still inside the client; the
        traffic manager's destructor would call the dead server), and its port taken for this process."""
        self.watchdog.abandon(self.client, self._tm)
        if self._tm is not None:
            _ABANDONED_TM_PORTS.add(self.tm_port)

    def map_names(self) -> list[str]:
        return sorted({map_basename(m) for m in self.call("listing maps", self.client.get_available_maps)})

    def load_map(self, name: str, digest: str | None = None) -> Any:
        """The world with map ``name`` (loaded only when the server runs another one). With ``digest`` (a
        catalog's ``map_digest``) the map is the one whose OpenDRIVE has that SHA-256, whatever its name:
        every generated world is called "OpenDriveMap", so a name alone would run one export's scenes on
        another's roads."""
        world = self.call("reading the world", self.client.get_world)
        if map_basename(self.map_of(world).name) == name and self._is(world, digest):
            return world  # already loaded (also a world made with generate_opendrive_world, which no list holds)
        names = self.map_names()
        if name not in names:
            if map_basename(self.map_of(world).name) == name:  # a generated world: only its content tells
                raise self._other_map(name, digest, world)
            raise UserInputError(f"CARLA map '{name}' is not on the server {self.host}:{self.port}; "
                                 f"available: {', '.join(names)}")
        self.client.set_timeout(self.load_timeout)
        try:
            self.call_within(f"loading map {name}", deadline_for(self.load_timeout), self.client.load_world, name)
        finally:
            self.client.set_timeout(self.timeout)
        world = self.call("reading the world", self.client.get_world)
        if not self._is(world, digest):
            raise self._other_map(name, digest, world)
        return world

    def map_digest(self, world: Any) -> str:
        """SHA-256 of the world's OpenDRIVE (cached per world: the text is the whole map)."""
        if self._digest_cache is None or self._digest_cache[0] != world.id:
            carla_map = self.map_of(world)
            self._digest_cache = (world.id, opendrive_digest(self.call("reading the OpenDRIVE map",
                                                                       carla_map.to_opendrive)))
        return self._digest_cache[1]

    def _is(self, world: Any, digest: str | None) -> bool:
        return digest is None or self.map_digest(world) == digest

    def _other_map(self, name: str, digest: str | None, world: Any) -> UserInputError:
        return UserInputError(
            f"the catalog's map '{name}' has OpenDRIVE digest {short(digest or '')}, but the server "
            f"{self.host}:{self.port} runs a map of that name with digest {short(self.map_digest(world))}: another "
            "map under the same name (CARLA names every generated world 'OpenDriveMap'). Load the map the catalog "
            "was made on (the same .xodr), or make the catalog again on this one (genesis-rl scenes --backend carla)")

    def map_of(self, world: Any) -> Any:
        """The world's ``carla.Map`` (fetching it transfers the OpenDRIVE file: cached per world)."""
        if self._map_cache is None or self._map_cache[0] != world.id:
            self._map_cache = (world.id, self.call("reading the map", world.get_map))
        return self._map_cache[1]

    def route_planner(self, carla_map: Any, world_id: int = -1) -> Any:
        """The built-in controller's :class:`~genesis_rl.sim.carla.route.RoutePlanner` for ``carla_map``
        (reading the topology takes a while on a town: built once per map and connection), and the map's
        speed limits from its OpenDRIVE."""
        from genesis_rl.sim.carla.route import RoutePlanner, speed_limits

        key = (int(world_id), str(carla_map.name))  # a world generated anew under the same name is another map
        if self._planner is None or self._planner[0] != key:
            xodr = self.call("reading the OpenDRIVE map", carla_map.to_opendrive)
            self._planner = (key, RoutePlanner(carla_map), speed_limits(xodr))
        return self._planner[1], self._planner[2]

    def create_simulation(self, scene: Scene, *, seed: int, weather: Weather | None = None,
                          camera: CameraConfig | None = None, render: bool = True) -> CarlaSimulation:
        return CarlaSimulation(self, scene, seed, weather or Weather.default(), camera or CameraConfig(), render)

    def traffic_manager(self) -> Any:
        """This connection's traffic manager (started on ``tm_port`` once, shut down by :meth:`close`); a port
        taken on this machine fails at once, by name (:mod:`~genesis_rl.sim.carla.ports`)."""
        if self._tm is None:
            if self.tm_port in _ABANDONED_TM_PORTS:  # a lost server's traffic manager of this process holds it
                port = free_port()
                warnings.warn(f"CARLA traffic manager port {self.tm_port} is held by the traffic manager of a lost "
                              f"server; this connection uses port {port}", RuntimeWarning, stacklevel=2)
                self.tm_port = port
            if self.tm_port not in _OPEN_TM_PORTS:
                ensure_free(self.tm_port)
            try:
                self._tm = self.call(f"starting the traffic manager on port {self.tm_port}",
                                     self.client.get_trafficmanager, self.tm_port)
            except RuntimeError as err:
                if not is_bind_error(err):
                    raise
                raise TrafficManagerPortBusy(busy_message(self.tm_port, f"CARLA: {err}")) from None
            _OPEN_TM_PORTS.add(self.tm_port)
        return self._tm

    def close(self) -> None:
        """Destroy live episodes and shut the traffic manager down: a reconnect in this process then starts
        a new one instead of getting this one back, tied to a dead connection."""
        for sim in list(self._live):
            sim.destroy()
        self._live.clear()
        if self._tm is not None and self.lost:
            self._tm = None  # abandoned, never shut down: see _give_up
        elif self._tm is not None:
            tm, self._tm = self._tm, None
            _OPEN_TM_PORTS.discard(self.tm_port)
            try:
                self.call(f"shutting the traffic manager on port {self.tm_port} down", tm.shut_down)
            except RuntimeError as err:
                warnings.warn(f"CARLA traffic manager on port {self.tm_port}: shutting down failed ({err})",
                              RuntimeWarning, stacklevel=2)


class CarlaSimulation(Simulation):
    """One episode on a CARLA server. Vehicle ids are indices in ``scene.vehicles`` (the ego is 0); a
    vehicle that could not be spawned (its place taken) is missing from :meth:`actors`."""

    snapshot_unsupported = (
        "the CARLA backend cannot save and restore a running world: the server's physics, its traffic manager and "
        "its sensors keep state that CARLA's Python API can neither read nor set (a world is only rebuilt from "
        "its start). Use an adversary that replays episodes from their start (cmaes, cem, random_search, mcts) "
        "or run goexplore on the lite backend")

    def __init__(self, backend: CarlaBackend, scene: Scene, seed: int, weather: Weather, camera: CameraConfig,
                 render: bool) -> None:
        self._backend = backend
        self.scene, self.seed, self.camera, self.render = scene, int(seed), camera, bool(render)
        self._weather = weather
        self._applied_weather: Weather | None = None  # what the server has; None: nothing sent yet
        self._control = VehicleControl()
        self._applied_control: VehicleControl | None = None
        self._step = 0
        self._actors: dict[int, Any] = {}  # scene index -> carla.Vehicle
        self._index_of: dict[int, int] = {}  # carla actor id -> scene index
        self._sensors: list[Any] = []
        self._queues: dict[str, FrameQueue] = {}
        self._images: dict[str, Any] = {}
        self._hits: list[tuple[int, int]] = []  # (frame, other actor id) from the collision sensor
        self._hits_lock = threading.Lock()
        self._contacts = ContactTracker()
        self._history: dict[int, tuple[int, dict[int, np.ndarray]]] = {}  # frame -> (step, velocities)
        self._boxes: dict[int, Any] = {}  # scene index -> bounding box (see _box)
        self._counted: tuple[str, int] | None = None  # the server this live episode is counted on
        self._blueprints: Any = None
        self._lights: dict[str, Any] = {}  # landmark id -> carla.TrafficLight (None: no actor for it)
        self._original_settings: Any = None
        self._tm: Any = None
        self._lead_braking = LeadBraking()  # the lead_decel knob (actor_control.py)
        self._cut_in = CutIn()  # the cut_in_ttc knob
        self._traffic_behaviour = TrafficBehaviour()  # the traffic manager's per-vehicle knobs
        self._braking_events: list[ActorEvent] = []
        self._destroyed = False
        self.skipped: list[int] = []  # scene indices that could not be spawned
        backend._live.add(self)
        try:
            self._setup()
        except BaseException:
            self.destroy()
            raise

    # -- setup -------------------------------------------------------------------------------------------
    def _setup(self) -> None:
        carla = require_carla()
        b, scene = self._backend, self.scene
        self.world = b.load_map(scene.map, scene.map_digest)
        self.map = b.map_of(self.world)
        specs = plan_scene(scene, self.map)  # fails on a foreign catalog before the server is touched
        found = b.call("reading settings", self.world.get_settings)
        server = (b.host, b.port)
        if found.synchronous_mode and not _OUR_EPISODES.get(server):  # a dead client's, or another live run's
            b.call("watching for another client's ticks", check_not_driven, self.world, f"{b.host}:{b.port}")
        _OUR_EPISODES[server] = _OUR_EPISODES.get(server, 0) + 1
        self._counted = server
        self._original_settings = original_settings(found, f"{b.host}:{b.port}")
        settings = b.call("reading settings", self.world.get_settings)
        settings.synchronous_mode = True
        settings.fixed_delta_seconds = self.dt
        settings.no_rendering_mode = not self.render
        b.call("switching to synchronous mode", self.world.apply_settings, settings)
        tm_seed = episode_seed(scene, self.seed)
        self._tm = tm = b.traffic_manager()
        b.call("setting the traffic manager up", _tm_setup, tm, tm_seed)
        self._spawn(specs, tm_seed)
        ego = self._actors[0]
        if self.render:
            self._add_camera("rgb", "sensor.camera.rgb", ego)
            self._add_camera("depth", "sensor.camera.depth", ego)
        library = self._library()
        hit = b.call("spawning the collision sensor", self.world.spawn_actor,
                     library.find("sensor.other.collision"), carla.Transform(), attach_to=ego)
        self._sensors.append(hit)
        b.call("listening to the collision sensor", hit.listen, self._on_collision)
        self._k = self.camera.intrinsics()
        self._advance(0)  # first frame for observe() at step 0; the spawned cars settle onto the road
        with self._hits_lock:
            self._hits.clear()

    def _library(self) -> Any:
        if self._blueprints is None:
            self._blueprints = self._backend.call("reading the blueprint library", self.world.get_blueprint_library)
        return self._blueprints

    def _spawn(self, specs: list[SpawnSpec], tm_seed: int) -> None:
        carla = require_carla()
        b = self._backend
        cmds = spawn_commands(specs, self._library(), b.tm_port, tm_seed)
        responses = b.call("spawning the scene", b.client.apply_batch_sync, cmds, True)
        errors = {}
        for spec, resp in zip(specs, responses, strict=True):
            if resp.error:
                errors[spec.index] = resp.error
                self.skipped.append(spec.index)
            else:
                self._index_of[resp.actor_id] = spec.index  # recorded first: destroy() removes them on failure
        if 0 in errors:
            loc = specs[0].transform.location
            raise UserInputError(
                f"CARLA refused to spawn the ego of scene {self.scene.index} at ({loc.x:.1f}, {loc.y:.1f}) "
                f"on {self.scene.map}: {errors[0]}. Another actor is probably there (a crashed run leaves "
                "actors behind: restart the server or destroy them)"
            )
        if self.skipped:
            warnings.warn(f"scene {self.scene.index}: CARLA could not spawn vehicles {self.skipped} (place taken)",
                          RuntimeWarning, stacklevel=3)
        actors = b.call("reading the spawned actors", self.world.get_actors, list(self._index_of))
        self._actors = {self._index_of[a.id]: a for a in actors}
        by_index = {s.index: s for s in specs}
        batch = [carla.command.ApplyTargetVelocity(a.id, initial_velocity(by_index[i]))
                 for i, a in self._actors.items() if by_index[i].speed > 0]
        for i, actor in self._actors.items():
            ap = by_index[i].autopilot
            if ap:  # the traffic manager honours target speed and standstill gap; stops and noise are lite-only
                if "target_speed" in ap:
                    b.call("setting an NPC's speed", self._tm.set_desired_speed, actor, float(ap["target_speed"]) * 3.6)
                if "min_gap" in ap:
                    b.call("setting an NPC's gap", self._tm.distance_to_leading_vehicle, actor, float(ap["min_gap"]))
        if batch:
            b.call("setting initial speeds", b.client.apply_batch_sync, batch, False)

    def _add_camera(self, name: str, blueprint: str, ego: Any) -> None:
        cam = self.camera
        bp = self._library().find(blueprint)
        bp.set_attribute("image_size_x", str(cam.width))
        bp.set_attribute("image_size_y", str(cam.height))
        bp.set_attribute("fov", f"{cam.fov_deg:g}")
        bp.set_attribute("sensor_tick", "0.0")  # every tick
        for key, value in CAMERA_ATTRIBUTES.get(blueprint, {}).items():
            bp.set_attribute(key, value)
        mount = camera_mount(cam.mount_x, cam.mount_y, cam.mount_z, cam.pitch_deg)
        sensor = self._backend.call(f"spawning the {name} camera", self.world.spawn_actor, bp, mount, attach_to=ego)
        self._sensors.append(sensor)
        q = FrameQueue(name)
        self._queues[name] = q
        self._backend.call(f"listening to the {name} camera", sensor.listen, q.put)

    def _on_collision(self, event: Any) -> None:
        with self._hits_lock:
            self._hits.append((int(event.frame), int(event.other_actor.id) if event.other_actor else -1))

    # -- stepping ----------------------------------------------------------------------------------------
    def set_weather(self, weather: Weather) -> None:
        """Every knob for the next tick: weather fields go to ``world.set_weather``, ``lead_decel`` to per-actor
        control (``actor_control.py``). An actor knob this backend does not realise is refused, not ignored."""
        moved = [k.name for k in KNOBS.values() if k.is_actor and k.name not in CARLA_ACTOR_KNOBS
                 and weather[k.name] != k.default]
        if moved:
            raise UserInputError(f"actor knob(s) {moved} have no CARLA realisation yet; realised: "
                                 f"{', '.join(CARLA_ACTOR_KNOBS)} (docs/actors.md)")
        self._weather = weather

    def _actor_id(self, index: int) -> int | None:
        actor = self._actors.get(index)
        return None if actor is None else int(actor.id)

    def _velocity(self, index: int) -> tuple[float, float, float]:
        s = self._snapshot.find(self._actors[index].id)
        if s is None:
            return (0.0, 0.0, 0.0)
        v = s.get_velocity()
        return (float(v.x), float(v.y), float(v.z))

    def apply_ego_control(self, control: VehicleControl) -> None:
        self._control = control

    def _advance(self, step: int) -> int:
        """Push weather and control, tick the server, and collect this frame's sensor data (the frame of ``step``)."""
        carla = require_carla()
        b = self._backend
        if self._weather != self._applied_weather:
            b.call("setting the weather", self.world.set_weather, to_carla(self._weather))
            self._applied_weather = self._weather
        now = self._step * self.dt  # the episode time this tick starts from
        braking_before = self._lead_braking.vehicle
        brake = self._lead_braking.commands(carla, b.tm_port, float(self._weather["lead_decel"]), self.dt,
                                            self.lead, self._actor_id, self._velocity) if self._actors else []
        if brake:
            b.call("braking the lead (lead_decel)", b.client.apply_batch_sync, brake, False)
        if braking_before < 0 <= self._lead_braking.vehicle:  # brake lights on: perceivable at once
            self._braking_events.append(ActorEvent("lead_braking", self._lead_braking.vehicle, now, now))
        # each watched call costs a thread (the watchdog): none at all while these knobs sit at their defaults
        ttc, off = float(self._weather["cut_in_ttc"]), KNOBS["cut_in_ttc"].default
        if self._actors and self._cut_in.wanted(ttc, off):
            b.call("changing a neighbour's lane (cut_in_ttc)", self._cut_in.step, self._tm, ttc, off, now,
                   self._neighbours, self._actors.get, self._offset_from_ego_lane,
                   float(self._weather["cut_in_relative_speed"]), float(np.linalg.norm(self._velocity(0))),
                   float(self._weather["vehicle_percentage_speed_difference"]))
        if self._actors and self._traffic_behaviour.changed(self._weather.values):
            npcs = [a for i, a in sorted(self._actors.items())  # held ones keep their speed until released
                    if i != 0 and i != self._lead_braking.vehicle and i not in self._cut_in.held]
            b.call("setting the traffic's behaviour (traffic manager)", self._traffic_behaviour.apply, self._tm,
                   self._weather.values, npcs)
        if self._control != self._applied_control:
            c = self._control
            b.call("applying the ego's control", self._actors[0].apply_control,
                   carla.VehicleControl(throttle=c.throttle, steer=c.steer, brake=c.brake))
            self._applied_control = c
        frame = b.call(f"ticking (step {self._step})", self.world.tick, b.timeout)
        self._snapshot = self.world.get_snapshot()
        self._history[int(frame)] = (step, self._velocities())
        for old in sorted(self._history)[:-VELOCITY_HISTORY]:
            del self._history[old]
        for name, q in self._queues.items():
            try:
                self._images[name] = q.get(frame, b.timeout)
            except TimeoutError as err:
                raise CarlaServerLost(f"CARLA server {b.host}:{b.port}: {err}; the episode is lost") from err
        return frame

    def _velocities(self) -> dict[int, np.ndarray]:
        out = {}
        for i, a in self._actors.items():
            s = self._snapshot.find(a.id)
            if s is not None:
                v = s.get_velocity()
                out[i] = np.array([v.x, v.y, v.z])
        return out

    def tick(self) -> TickResult:
        if self._destroyed:
            raise RuntimeError("this simulation was destroyed")
        frame = self._advance(self._step + 1)
        self._step += 1
        return TickResult(self._step, self._step * self.dt, self._collisions(frame))

    def _before(self, frame: int) -> tuple[int, dict[int, np.ndarray]]:
        """The step of ``frame`` and the velocities just before it (the snapshot of the frame before: the
        impact's own snapshot already holds post-impact speeds). The oldest held when ``frame`` is older."""
        held = sorted(self._history)
        prior = [f for f in held if f < frame] or held[:1]
        step = self._history[frame][0] if frame in self._history else self._step
        return step, self._history[prior[-1]][1] if prior else {}

    def _collisions(self, frame: int) -> list[Collision]:
        """The ego's new contacts this tick (the sensor reports every frame of a contact, on its own stream;
        :class:`~genesis_rl.sim.carla.contacts.ContactTracker` reports each contact's start once, as the lite
        backend does). Static objects have vehicle id -1. A contact's speeds and step are those of the event's
        own frame: an event that arrives a tick late is not given the post-impact speeds of the tick it is
        read at."""
        with self._hits_lock:
            now = [h for h in self._hits if h[0] <= frame]
            self._hits = [h for h in self._hits if h[0] > frame]
        zero = np.zeros(3)
        out = []
        for hit_frame, other in self._contacts.starts(now):
            step, before = self._before(hit_frame)
            j = self._index_of.get(other, -1)
            va, vb = before.get(0, zero), before.get(j, zero) if j >= 0 else zero
            out.append(Collision(step, 0, j, float(np.linalg.norm(va[:2])), float(np.linalg.norm(vb[:2])),
                                 float(np.linalg.norm((va - vb)[:2]))))
        return out

    # -- sensing -----------------------------------------------------------------------------------------
    def observe(self) -> SensorFrame:
        if not self.render:
            raise RuntimeError("this simulation was created with render=False")
        cam = self.camera
        rgb_img, depth_img = self._images["rgb"], self._images["depth"]
        rgb = bgra_to_rgb(rgb_img.raw_data, cam.width, cam.height)
        depth = decode_depth(depth_img.raw_data, cam.width, cam.height)
        vehicles = []
        for i, a in self._actors.items():
            s = self._snapshot.find(a.id)
            if i != 0 and s is not None:
                vehicles.append((i, self._box(i), s.get_transform()))
        boxes = ground_truth_boxes(vehicles, depth_img.transform, self._k, depth, cam.max_range)
        return SensorFrame(self._step, rgb, depth, boxes)

    def actors(self) -> list[ActorState]:
        out = []
        for i in sorted(self._actors):
            a = self._actors[i]
            s = self._snapshot.find(a.id)
            if s is None:
                continue
            v, ext, spec = s.get_velocity(), self._box(i).extent, self.scene.vehicles[i]
            out.append(ActorState(i, spec.role, spec.make, *pose_from_carla(s.get_transform()), math.hypot(v.x, v.y),
                                  2.0 * ext.x, 2.0 * ext.y, 2.0 * ext.z))
        return out

    def lead(self) -> LeadInfo | None:
        tf, wp = self._ego_waypoint()
        if wp is None:
            return None
        ids, xy, half, speed = self._others()
        return lead_on_path(lane_path(wp), np.array([tf.location.x, tf.location.y]), self._box(0).extent.x,
                            xy, half, speed, np.array(ids), lane_half_width=wp.lane_width / 2.0)

    def _ego_waypoint(self) -> Any:
        carla = require_carla()
        tf = self._snapshot.find(self._actors[0].id).get_transform()
        return tf, self.map.get_waypoint(tf.location, project_to_road=True, lane_type=carla.LaneType.Driving)

    def _others(self) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
        """Scene index, (x, y), half length and speed of every vehicle but the ego."""
        ids, xy, half, speed = [], [], [], []
        for i, a in self._actors.items():
            s = self._snapshot.find(a.id)
            if i == 0 or s is None:
                continue
            loc, v = s.get_transform().location, s.get_velocity()
            ids.append(i)
            xy.append((loc.x, loc.y))
            half.append(self._box(i).extent.x)
            speed.append(math.hypot(v.x, v.y))
        return ids, np.array(xy).reshape(-1, 2), np.array(half), np.array(speed)

    def _neighbours(self) -> list[Neighbour]:
        """The nearest vehicle ahead in each neighbouring lane of the ego's that runs its way (the cut-in's
        candidates), measured along that lane."""
        tf, wp = self._ego_waypoint()
        if wp is None:
            return []
        ids, xy, half, speed = self._others()
        ego_v = self._snapshot.find(self._actors[0].id).get_velocity()
        ego_speed = math.hypot(ego_v.x, ego_v.y)
        out = []
        for side, to_right in ((wp.get_left_lane(), True), (wp.get_right_lane(), False)):
            if side is None or side.lane_type != wp.lane_type or side.lane_id * wp.lane_id <= 0:
                continue  # no lane there, not a driving lane, or the oncoming carriageway
            found = lead_on_path(lane_path(side), np.array([tf.location.x, tf.location.y]), self._box(0).extent.x,
                                 xy, half, speed, np.array(ids), lane_half_width=side.lane_width / 2.0)
            if found is not None:
                out.append(Neighbour(found.vehicle_id, found.gap, ego_speed - found.speed, to_right))
        return out

    def neighbour_ahead(self) -> LeadInfo | None:
        near = self._neighbours() if self._actors else []
        if not near:
            return None
        n = min(near, key=lambda x: x.gap)
        ego_v = self._snapshot.find(self._actors[0].id).get_velocity()
        return LeadInfo(n.vehicle, n.gap, math.hypot(ego_v.x, ego_v.y) - n.closing)

    def _offset_from_ego_lane(self, index: int) -> float | None:
        """Vehicle ``index``'s distance [m] from the centre line of the ego's lane (None: gone)."""
        a = self._actors.get(index)
        s = None if a is None else self._snapshot.find(a.id)
        tf, wp = self._ego_waypoint()
        if s is None or wp is None:
            return None
        loc = s.get_transform().location
        return path_offset(lane_path(wp, length=PATH_LENGTH + 20.0), np.array([loc.x, loc.y]))

    def actor_events(self) -> list[ActorEvent]:
        return sorted(self._braking_events + self._cut_in.events(), key=lambda e: e.onset_s)

    def context_extras(self) -> dict[str, Any]:
        """For the built-in controller: how to plan its route on this map, the planner (built once per map),
        the map's speed limits and the server's light states."""
        from genesis_rl.sim.carla.route import route_from_context

        planner, limits = self._backend.route_planner(self.map, self.world.id)
        return {"plan_route": route_from_context, "signal_state": self.light_state, "route_planner": planner,
                "speed_limits": limits}

    def light_state(self, landmark: Any, time_s: float) -> str:
        """The state of the traffic light that ``landmark`` (a signal of the map) belongs to, as the server
        runs it now: 'red', 'yellow' or 'green' (off or unknown lights read green, as BehaviorAgent treats
        them). ``time_s`` is unused: the server keeps its own light cycle."""
        carla = require_carla()
        if landmark.id not in self._lights:
            self._lights[landmark.id] = self._backend.call("reading a traffic light", self.world.get_traffic_light,
                                                           landmark)
        light = self._lights[landmark.id]
        if light is None:
            return "green"
        states = {carla.TrafficLightState.Red: "red", carla.TrafficLightState.Yellow: "yellow"}
        return states.get(light.state, "green")

    def _box(self, i: int) -> Any:
        """Vehicle ``i``'s bounding box; where the blueprint reports none (CARLA's one bus had a zero box in
        older releases: no ground-truth box, no lead gap) a box of its catalog make's size, with a warning."""
        if i not in self._boxes:
            box = self._actors[i].bounding_box
            if min(box.extent.x, box.extent.y, box.extent.z) <= MIN_EXTENT:
                carla = require_carla()
                make = MAKES[self.scene.vehicles[i].make]
                warnings.warn(f"CARLA reports a zero bounding box for vehicle {i} ({self._actors[i].type_id}); "
                              f"using its make's size ({make.length:g} x {make.width:g} x {make.height:g} m)",
                              RuntimeWarning, stacklevel=3)
                box = carla.BoundingBox(carla.Location(0.0, 0.0, make.height / 2.0),
                                        carla.Vector3D(make.length / 2.0, make.width / 2.0, make.height / 2.0))
            self._boxes[i] = box
        return self._boxes[i]

    def carla_actor_ids(self) -> list[int]:
        """CARLA ids of everything this episode spawned (vehicles, then sensors), e.g. to check teardown."""
        return list(self._index_of) + [s.id for s in self._sensors]

    # -- teardown ----------------------------------------------------------------------------------------
    def destroy(self) -> None:
        """Stop and destroy sensors and vehicles, restore the server's settings. Every part runs even when
        an earlier one fails (problems are warned about, never raised: this runs while another error may be
        propagating)."""
        if self._destroyed:
            return
        self._destroyed = True
        self._backend._live.discard(self)
        if self._counted is not None:
            _OUR_EPISODES[self._counted] -= 1
            self._counted = None
        carla = require_carla()
        b, problems = self._backend, []
        if b.lost:  # the watchdog gave the server up: asking it anything would only wait again
            self._sensors, self._actors, self._queues, self._index_of = [], {}, {}, {}
            warnings.warn(f"CARLA server {b.host}:{b.port} was given up ({b.watchdog.lost}): this episode's actors "
                          "and settings are left on it; restart the server", RuntimeWarning, stacklevel=2)
            return
        for s in self._sensors:
            try:
                b.call(f"stopping sensor {s.id}", s.stop)
            except RuntimeError as err:
                problems.append(f"stopping sensor {s.id}: {err}")
        ids = [s.id for s in self._sensors] + list(self._index_of)
        if ids:
            try:  # tick with it in synchronous mode, so the server processes the removal now
                sync = self._original_settings is not None
                b.call("destroying the episode's actors", b.client.apply_batch_sync,
                       [carla.command.DestroyActor(i) for i in ids], sync)
            except RuntimeError as err:
                problems.append(f"destroying actors {ids}: {err}")
        if self._original_settings is not None:
            try:
                b.call("restoring world settings", self.world.apply_settings, self._original_settings)
            except RuntimeError as err:
                problems.append(f"restoring world settings: {err}")
        if self._tm is not None:
            try:
                was_sync = self._original_settings is not None and self._original_settings.synchronous_mode
                b.call("restoring the traffic manager", self._tm.set_synchronous_mode, bool(was_sync))
            except RuntimeError as err:
                problems.append(f"restoring the traffic manager: {err}")
        self._sensors, self._actors, self._queues, self._index_of = [], {}, {}, {}
        if problems:
            warnings.warn(f"CARLA teardown at {b.host}:{b.port} incomplete: {'; '.join(problems)}. If the server "
                          "stays in synchronous mode, restart it", RuntimeWarning, stacklevel=2)
