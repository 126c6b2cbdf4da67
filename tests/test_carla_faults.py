"""The CARLA review's server-handling faults, checked offline: fake client objects for the control flow
(they record what the backend asks of a server), the real ``carla`` module where it is needed."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import pytest

pytest.importorskip("carla")

from genesis_rl.sim.carla import backend as backend_module  # noqa: E402
from genesis_rl.sim.carla.actor_control import CutIn, LeadBraking, TrafficBehaviour  # noqa: E402
from genesis_rl.sim.carla.backend import (  # noqa: E402
    CAMERA_ATTRIBUTES,
    CarlaBackend,
    CarlaSimulation,
    original_settings,
)
from genesis_rl.sim.carla.connection import CarlaServerLost  # noqa: E402
from genesis_rl.sim.carla.contacts import CONTACT_GAP, ContactTracker  # noqa: E402
from genesis_rl.sim.interface import CameraConfig  # noqa: E402
from genesis_rl.world.knobs import Weather  # noqa: E402

TIMEOUT = RuntimeError("time-out of 10000ms while waiting for the simulator, make sure the simulator is ready")


class FakeTM:
    def __init__(self, port: int) -> None:
        self.port, self.shut = port, 0

    def shut_down(self) -> None:
        self.shut += 1


class FakeBlueprint:
    def __init__(self, name: str) -> None:
        self.name, self.attributes = name, {}

    def set_attribute(self, key: str, value: str) -> None:
        self.attributes[key] = value


class FakeSensor:
    id = 99

    def listen(self, fn) -> None:
        self.fn = fn


class FakeWorld:
    id = 1

    def __init__(self, fail: str | None = None) -> None:
        self.fail, self.blueprints, self.spawned = fail, {}, []

    def get_map(self):
        if self.fail == "map":
            raise TIMEOUT
        return SimpleNamespace(name="Carla/Maps/Town05")

    def get_blueprint_library(self):
        if self.fail == "library":
            raise TIMEOUT
        world = self
        return SimpleNamespace(find=lambda name: world.blueprints.setdefault(name, FakeBlueprint(name)))

    def spawn_actor(self, bp, transform, attach_to=None):
        self.spawned.append(bp)
        return FakeSensor()


class FakeClient:
    def __init__(self, world: FakeWorld) -> None:
        self.world, self.tms = world, []

    def get_available_maps(self):
        return ["/Game/Carla/Maps/Town05", "/Game/Carla/Maps/Town10HD_Opt"]

    def get_world(self):
        return self.world

    def get_trafficmanager(self, port: int):
        tm = FakeTM(port)
        self.tms.append(tm)
        return tm

    def set_timeout(self, t: float) -> None:
        pass


@pytest.fixture
def fake_server(monkeypatch):
    """CarlaBackend(...) connects to a FakeClient: ``.clients`` made so far, ``.fail`` what the world's
    next reads time out on."""
    server = SimpleNamespace(clients=[], fail=None)

    def connect(host, port, timeout, tm_port=None):
        server.clients.append(FakeClient(FakeWorld(server.fail)))
        return server.clients[-1]

    monkeypatch.setattr(backend_module, "connect", connect)
    return server


def test_close_shuts_the_traffic_manager_down_and_a_reconnect_gets_a_new_one(fake_server) -> None:
    b = CarlaBackend("localhost", 2000, tm_port=8000)
    tm = b.traffic_manager()
    assert b.traffic_manager() is tm and tm.port == 8000  # one per connection
    b.close()
    assert tm.shut == 1
    b.close()
    assert tm.shut == 1  # closing twice is harmless
    again = CarlaBackend("localhost", 2000, tm_port=8000)  # the campaign's reconnect after a lost server
    assert again.traffic_manager() is not tm and fake_server.clients[-1].tms[-1].shut == 0


@pytest.mark.parametrize("fail", ["map", "library"])
def test_map_and_blueprint_reads_are_retried_calls(fake_server, fail) -> None:
    fake_server.fail = fail
    b = CarlaBackend("localhost", 2000)
    if fail == "map":
        with pytest.raises(CarlaServerLost, match="localhost:2000 stopped answering while reading the map"):
            b.load_map("Town05")
    else:
        sim = object.__new__(CarlaSimulation)
        sim._backend, sim.world, sim._blueprints = b, b.client.get_world(), None
        with pytest.raises(CarlaServerLost, match="while reading the blueprint library"):
            sim._library()


def test_a_server_left_in_synchronous_mode_is_restored_to_asynchronous() -> None:
    left = SimpleNamespace(synchronous_mode=True, fixed_delta_seconds=0.05, no_rendering_mode=False)
    with pytest.warns(RuntimeWarning, match="was in synchronous mode"):
        restored = original_settings(left, "localhost:2000")
    assert (restored.synchronous_mode, restored.fixed_delta_seconds) == (False, None)
    fine = SimpleNamespace(synchronous_mode=False, fixed_delta_seconds=None, no_rendering_mode=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert original_settings(fine, "localhost:2000") is fine


def test_rgb_camera_adapts_its_exposure_at_once(fake_server) -> None:
    b = CarlaBackend("localhost", 2000)
    sim = object.__new__(CarlaSimulation)
    sim._backend, sim.world, sim._blueprints = b, b.client.get_world(), None
    sim.camera, sim._sensors, sim._queues = CameraConfig(), [], {}
    sim._add_camera("rgb", "sensor.camera.rgb", ego=None)
    sim._add_camera("depth", "sensor.camera.depth", ego=None)
    rgb, depth = (sim.world.blueprints[n].attributes for n in ("sensor.camera.rgb", "sensor.camera.depth"))
    assert rgb["exposure_speed_up"] == rgb["exposure_speed_down"] == "100" and rgb["exposure_mode"] == "histogram"
    assert CAMERA_ATTRIBUTES["sensor.camera.rgb"].items() <= rgb.items()
    assert "exposure_speed_up" not in depth and depth["image_size_x"] == "320"


def test_contacts_start_once_and_late_events_of_a_contact_are_not_new() -> None:
    t = ContactTracker()
    assert t.update([(10, 5)]) == [5]
    assert t.update([(11, 5), (12, 5)]) == []  # the same contact, one event per frame
    assert t.update([(12, 5), (11, 7)]) == [7]  # a late event of contact 5; vehicle 7 is new
    assert t.update([(12 + CONTACT_GAP, 5)]) == []  # within the gap: still the same contact
    assert t.update([(13 + 2 * CONTACT_GAP + 1, 5)]) == [5]  # after a gap: a second collision
    assert t.update([(40, -1), (40, -1), (41, 8)]) == [-1, 8]


def test_train_releases_the_simulator_when_the_first_episode_fails(monkeypatch) -> None:
    from genesis_rl.training import train as train_module

    closed = []

    class Refusing:
        def __init__(self, config) -> None:
            pass

        def reset(self, seed=None):
            raise NotImplementedError("this system refuses the map")

        def close(self) -> None:
            closed.append(True)

    monkeypatch.setattr(train_module, "GenesisEnv", Refusing)
    monkeypatch.setattr(train_module, "EnvConfig", lambda **kw: kw)
    with pytest.raises(NotImplementedError):
        train_module._make_env({}, 0, 0, 0)()
    assert closed == [True]


def test_carla_port_takes_one_server_per_process() -> None:
    import argparse

    from genesis_rl.commands.cli_args import add_scale_arguments
    from genesis_rl.core.errors import UserInputError
    from genesis_rl.distributed.servers import parse_servers, servers_for_workers
    from genesis_rl.sim.backends import add_backend_arguments, servers_text, settings_from_args

    parser = argparse.ArgumentParser()
    add_backend_arguments(parser)
    add_scale_arguments(parser, "--workers")
    args = parser.parse_args(["--backend", "carla", "--carla-host", "sim", "--carla-port", "2000,3000"])
    assert servers_text(args) == "sim:2000,sim:3000" and settings_from_args(args).port == 2000
    servers = servers_for_workers("carla", parse_servers(servers_text(args)), 2)
    assert [(s.port, s.tm_port) for s in servers] == [(2000, 8000), (3000, 9000)]
    with pytest.raises(UserInputError, match="--workers = 3 but --carla-servers names 2"):
        servers_for_workers("carla", parse_servers(servers_text(args)), 3)
    both = parser.parse_args(["--carla-port", "2000,3000", "--carla-servers", "a:1,b:2"])
    with pytest.raises(UserInputError, match="give one"):
        servers_text(both)
    for bad in ("2000,2000", "0", "http"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--carla-port", bad])


def test_the_controller_gets_the_servers_light_states_and_one_planner_per_map(fake_server) -> None:
    import carla

    from genesis_rl.sim.carla.route import RoutePlanner, route_from_context
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive

    b = CarlaBackend("localhost", 2000)
    sim = object.__new__(CarlaSimulation)
    sim._backend, sim.world, sim._lights = b, b.client.get_world(), {}
    sim.map = carla.Map("urban", to_opendrive(load_map("urban")))
    asked = []
    lights = {"1": SimpleNamespace(state=carla.TrafficLightState.Red),
              "2": SimpleNamespace(state=carla.TrafficLightState.Yellow),
              "3": SimpleNamespace(state=carla.TrafficLightState.Off)}
    sim.world.get_traffic_light = lambda lm: asked.append(lm.id) or lights.get(lm.id)
    states = [sim.light_state(SimpleNamespace(id=i), 0.0) for i in ("1", "2", "3", "4", "1")]
    assert states == ["red", "yellow", "green", "green", "red"]  # off and unknown read green, as BehaviorAgent's
    assert asked == ["1", "2", "3", "4"]  # each light is looked up once
    extras = sim.context_extras()
    assert extras["plan_route"] is route_from_context and isinstance(extras["route_planner"], RoutePlanner)
    assert sim.context_extras()["route_planner"] is extras["route_planner"]  # built once per map
    assert extras["speed_limits"][0] == pytest.approx(12.0)


def test_the_carla_backend_imports_nothing_of_lite() -> None:
    """The backends stand side by side: what both need (route spacing, vehicle placement) is backend-neutral."""
    import ast
    from pathlib import Path

    import genesis_rl.sim.carla as pkg

    found = []
    for path in sorted(Path(pkg.__file__).parent.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            found += [f"{path.name}: {n}" for n in names if n.startswith("genesis_rl.sim.lite")]
    assert found == []


class _Vel:
    def __init__(self, x: float) -> None:
        self.x, self.y, self.z = x, 0.0, 0.0


class _Snapshot:
    """Velocities by CARLA actor id at one frame."""

    def __init__(self, speeds: dict[int, float]) -> None:
        self.speeds = speeds

    def find(self, actor_id: int):
        return SimpleNamespace(get_velocity=lambda: _Vel(self.speeds[actor_id]))


class TickingWorld(FakeWorld):
    """Frames from 100 on; ``speeds[frame]`` the snapshot of each; ``on_tick[frame]`` runs before the tick
    returns (a collision event delivered then); ``hang`` makes tick block until released."""

    def __init__(self, speeds: dict[int, dict[int, float]]) -> None:
        super().__init__()
        self.frame, self.speeds, self.on_tick = 99, speeds, {}

    def tick(self, timeout: float) -> int:
        self.frame += 1
        self.on_tick.get(self.frame, lambda: None)()
        return self.frame

    def get_snapshot(self):
        return _Snapshot(self.speeds[self.frame])


def _bare_simulation(backend, world):
    """A CarlaSimulation with an ego (CARLA id 10) and a lead (id 11), set up by hand on a fake world."""
    import threading

    from genesis_rl.sim.interface import VehicleControl
    from genesis_rl.world.knobs import Weather

    sim = object.__new__(CarlaSimulation)
    sim._backend, sim.world, sim._destroyed, sim._step = backend, world, False, 0
    sim._weather = sim._applied_weather = Weather.default()
    sim._control = sim._applied_control = VehicleControl()
    sim._actors = {0: SimpleNamespace(id=10), 1: SimpleNamespace(id=11)}
    sim._index_of, sim._queues, sim._images, sim._history, sim._boxes = {10: 0, 11: 1}, {}, {}, {}, {}
    sim._hits, sim._hits_lock, sim._contacts, sim._counted = [], threading.Lock(), ContactTracker(), None
    sim._lead_braking = LeadBraking()  # lead_decel stays 0: it sends nothing
    # the cut-in and the traffic knobs stay at their defaults: they ask nothing of the traffic manager
    sim._cut_in, sim._traffic_behaviour, sim._braking_events, sim._tm = CutIn(), TrafficBehaviour(), [], None
    return sim


def test_a_late_collision_event_gets_the_speeds_and_step_of_its_own_frame(fake_server) -> None:
    # the ego drives at 10 m/s into a lead at 4 m/s; the impact is frame 102 (step 2), after which the snapshot
    # holds the crash's speeds (3 and 5 m/s). Its event reaches the client only during the next tick.
    speeds = {100: {10: 10.0, 11: 4.0}, 101: {10: 10.0, 11: 4.0}, 102: {10: 3.0, 11: 5.0}, 103: {10: 2.0, 11: 5.0}}
    b = CarlaBackend("localhost", 2000)
    world = TickingWorld(speeds)
    sim = _bare_simulation(b, world)
    world.on_tick[103] = lambda: sim._on_collision(SimpleNamespace(frame=102, other_actor=SimpleNamespace(id=11)))
    sim._advance(0)  # frame 100, step 0
    assert sim.tick().collisions == [] and sim.tick().collisions == []  # frames 101, 102: no event yet
    (hit,) = sim.tick().collisions  # frame 103: the event of frame 102 arrives
    assert (hit.step, hit.vehicle_b) == (2, 1)
    assert (hit.speed_a, hit.speed_b, hit.relative_speed) == (10.0, 4.0, 6.0)  # before the fix: 3, 5, 2 at step 3


# -- issue 36: one traffic-manager port per run -----------------------------------------------------------------
def test_each_run_gets_the_traffic_manager_port_of_its_server(fake_server) -> None:
    """Two runs on one machine against servers 2000 and 3000 both opened a traffic manager on 8000, and the
    second failed with CARLA's bind error; the port now follows the server's (PORT + 6000) unless given."""
    import argparse

    from genesis_rl.sim.backends import add_backend_arguments, settings_from_args

    parser = argparse.ArgumentParser()
    add_backend_arguments(parser)
    ports = []
    for rpc in ("2000", "3000"):
        settings = settings_from_args(parser.parse_args(["--backend", "carla", "--carla-port", rpc]))
        b = CarlaBackend.from_settings(settings)
        ports.append(b.traffic_manager().port)
        b.close()
    assert ports == [8000, 9000]
    given = CarlaBackend.from_settings(settings_from_args(parser.parse_args(["--carla-port", "3000",
                                                                              "--carla-tm-port", "8123"])))
    assert given.tm_port == 8123


def _listening_port():
    import socket

    sock = socket.socket()
    sock.bind(("", 0))
    sock.listen(1)
    return sock, sock.getsockname()[1]


def test_a_traffic_manager_port_taken_on_this_machine_fails_at_once_by_name(fake_server) -> None:
    from genesis_rl.sim.carla.ports import TrafficManagerPortBusy

    sock, port = _listening_port()  # another run's traffic manager
    try:
        b = CarlaBackend("localhost", 2000, tm_port=port)
        with pytest.raises(TrafficManagerPortBusy, match=f"traffic manager's port {port} is taken on this machine"):
            b.traffic_manager()
        assert fake_server.clients[-1].tms == []  # the client was never asked
    finally:
        sock.close()


def test_carlas_bind_error_is_named(fake_server) -> None:
    """When the port is taken between the check and the client's bind, CARLA's raw RuntimeError (which no
    connection check recognised) is turned into the same named error (exit status 2)."""
    from genesis_rl.sim.carla.ports import TrafficManagerPortBusy

    b = CarlaBackend("localhost", 2000)

    def bind_error(port):
        raise RuntimeError("trying to create rpc server for traffic manager; but the system failed to create "
                           "because of bind error.")

    b.client.get_trafficmanager = bind_error
    with pytest.raises(TrafficManagerPortBusy, match="port 8000 is taken on this machine .*CARLA: trying") as err:
        b.traffic_manager()
    assert err.value.exit_code == 2


# -- issue 36: a map is known by its OpenDRIVE, not its name ----------------------------------------------------
class MapWorld(FakeWorld):
    """A server world running ``cmap`` (a real carla.Map: what generate_opendrive_world leaves loaded)."""

    def __init__(self, cmap, world_id: int) -> None:
        super().__init__()
        self.cmap, self.id = cmap, world_id

    def get_map(self):
        return self.cmap


def test_a_catalog_runs_only_on_the_map_it_was_made_on(fake_server) -> None:
    """Regression (issue 36): catalogs made on the urban and the highway exports both said 'OpenDriveMap',
    and load_map took any world of that name: one's scenes ran on the other's roads."""
    import hashlib
    import json

    import carla

    from genesis_rl.core.errors import UserInputError
    from genesis_rl.sim.carla.scenes import generate_catalog
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive
    from genesis_rl.world.scenes.catalog import parse_catalog

    urban, highway = (to_opendrive(load_map(n)) for n in ("urban", "highway"))
    made = generate_catalog(carla.Map("OpenDriveMap", urban), "OpenDriveMap", 2, seed=0, n_vehicles=3)
    digest = hashlib.sha256(urban.encode()).hexdigest()
    assert made.map_digest == digest and made.to_json()["map_digest"] == digest
    as_json = json.loads(json.dumps(made.to_json()))
    scene = parse_catalog(as_json).scene(1)
    assert scene.map_digest == digest

    b = CarlaBackend("localhost", 2000)
    b.client.world = MapWorld(carla.Map("OpenDriveMap", highway), world_id=7)
    with pytest.raises(UserInputError, match=f"digest {digest[:12]}, but the server localhost:2000 runs a map of "
                                             "that name with digest"):
        b.load_map(scene.map, scene.map_digest)
    b.client.world = right = MapWorld(carla.Map("OpenDriveMap", urban), world_id=8)
    assert b.load_map(scene.map, scene.map_digest) is right
    with pytest.raises(UserInputError, match="'map_digest' = 'x'; allowed: the SHA-256"):
        parse_catalog({**as_json, "map_digest": "x"})


# -- issue 36: a second live client is not taken for a dead one ---------------------------------------------------
class DrivenWorld(MapWorld):
    """A world in synchronous mode; ``ticker`` is what wait_for_tick meets: a frame (another client ticks)
    or the client's time-out (nobody does)."""

    def __init__(self, cmap, ticker) -> None:
        super().__init__(cmap, world_id=9)
        self.ticker, self.applied, self.watched = ticker, [], []

    def get_settings(self):
        return SimpleNamespace(synchronous_mode=True, fixed_delta_seconds=0.05, no_rendering_mode=False)

    def apply_settings(self, settings) -> None:
        self.applied.append(settings)

    def wait_for_tick(self, seconds: float):
        self.watched.append(seconds)
        return self.ticker()


@pytest.fixture(scope="module")
def urban_scene():
    import carla

    from genesis_rl.sim.carla.scenes import generate_catalog
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive

    cmap = carla.Map("OpenDriveMap", to_opendrive(load_map("urban")))
    return cmap, generate_catalog(cmap, "OpenDriveMap", 1, seed=3, n_vehicles=3).scene(0)


def test_a_server_another_client_ticks_is_refused_before_anything_is_changed(fake_server, urban_scene) -> None:
    """Regression (issue 36): any server in synchronous mode was taken for orphaned; a second run then ticked
    a server that another run drives, reseeded its traffic manager and at close made it asynchronous."""
    from genesis_rl.sim.carla.backend import ORPHAN_WATCH_S, ServerInUse

    cmap, scene = urban_scene
    b = CarlaBackend("localhost", 2000)
    b.client.world = world = DrivenWorld(cmap, lambda: SimpleNamespace(frame=5123))
    with pytest.raises(ServerInUse, match="another client ticks it \\(frame 5123") as err:
        CarlaSimulation(b, scene, 0, Weather.default(), CameraConfig(), render=False)
    assert err.value.exit_code == 2 and world.watched == [ORPHAN_WATCH_S]
    assert world.applied == [] and b.client.tms == []  # settings and traffic manager untouched


def test_a_server_nobody_ticks_is_taken_over_as_orphaned(fake_server, urban_scene) -> None:
    from genesis_rl.sim.carla.backend import check_not_driven

    def timeout():
        raise TIMEOUT

    world = DrivenWorld(urban_scene[0], timeout)
    assert check_not_driven(world, "localhost:2000", 0.5) is None and world.watched == [0.5]

    def refused():
        raise RuntimeError("rpc::rpc_error during call in function get_settings")

    with pytest.raises(RuntimeError, match="rpc_error"):  # a broken connection is not a quiet server
        check_not_driven(DrivenWorld(urban_scene[0], refused), "localhost:2000", 0.5)


def _free_tcp_port() -> int:
    from genesis_rl.sim.carla.ports import free_port

    return free_port()


def test_a_vehicle_without_a_bounding_box_gets_its_makes_size(fake_server) -> None:
    """Guard (issue 36, suspected): CARLA's one bus blueprint reported a zero bounding box in older releases,
    which would drop its ground-truth box and make a lead gap from its centre."""
    import carla

    from genesis_rl.world.scenes.vehicles import MAKES

    b = CarlaBackend("localhost", 2000)
    sim = _bare_simulation(b, FakeWorld())
    sim.scene = SimpleNamespace(vehicles=[SimpleNamespace(make="sedan"), SimpleNamespace(make="bus")])
    sim._actors[0].bounding_box = carla.BoundingBox(carla.Location(0, 0, 0.7), carla.Vector3D(2.4, 1.0, 0.7))
    sim._actors[1] = SimpleNamespace(id=11, type_id="vehicle.mitsubishi.fusorosa",
                                     bounding_box=carla.BoundingBox(carla.Location(), carla.Vector3D(0, 0, 0)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert sim._box(0).extent.x == pytest.approx(2.4)  # a real box is kept as it is
    with pytest.warns(RuntimeWarning, match="zero bounding box for vehicle 1 \\(vehicle.mitsubishi.fusorosa\\)"):
        bus = sim._box(1)
    bus_make = MAKES["bus"]
    assert (bus.extent.x, bus.extent.y, bus.extent.z) == pytest.approx(
        (bus_make.length / 2, bus_make.width / 2, bus_make.height / 2))


def test_a_second_connection_of_this_process_shares_its_open_traffic_manager(fake_server) -> None:
    """A campaign's counterfactual (oracle) env connects to the same server from the same process: the client
    hands it the traffic manager this process already runs on that port, which is not 'taken'."""
    import socket

    port = _free_tcp_port()
    listening = []

    def opens_port(p):  # the traffic manager's RPC server listens on its port
        sock = socket.socket()
        sock.bind(("", p))
        sock.listen(1)
        listening.append(sock)
        return FakeTM(p)

    try:
        first = CarlaBackend("localhost", 2000, tm_port=port)
        first.client.get_trafficmanager = opens_port
        first.traffic_manager()
        oracle = CarlaBackend("localhost", 2000, tm_port=port)
        assert oracle.traffic_manager().port == port  # not TrafficManagerPortBusy
        first.close()
        oracle.close()
    finally:
        for sock in listening:
            sock.close()
