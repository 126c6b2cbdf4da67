"""A hung simulator server costs one episode, never a campaign (issue 36): the watchdog around blocking
server calls, a campaign whose server's tick never returns, and the CARLA backend after such a hang."""

from __future__ import annotations

import json
import threading
import time
from types import SimpleNamespace

import pytest

from genesis_rl.core.errors import SimulatorLost
from genesis_rl.sim.lite.backend import LiteBackend, LiteSimulation
from genesis_rl.sim.watchdog import SimulatorHung, Watchdog

#: released when the module's tests end, so the stuck threads finish
RELEASE = threading.Event()


@pytest.fixture(autouse=True, scope="module")
def _release_stuck_threads():
    yield
    RELEASE.set()


def never_returns(*args):
    """A server call that blocks for good (CARLA's tick inside the traffic manager's untimed wait)."""
    RELEASE.wait()
    return 0


def test_a_call_past_its_deadline_loses_the_connection_and_later_calls_fail_at_once() -> None:
    dog = Watchdog("server a:1")
    assert dog.call("reading", 1.0, lambda x: x + 1, 41) == 42
    with pytest.raises(ValueError, match="bad blueprint"):  # the call's own errors come through as they are
        dog.call("spawning", 1.0, lambda: (_ for _ in ()).throw(ValueError("bad blueprint")))
    t0 = time.monotonic()
    with pytest.raises(SimulatorHung, match="server a:1 stopped answering: ticking did not return within 0.2 s"):
        dog.call("ticking", 0.2, never_returns)
    assert 0.2 <= time.monotonic() - t0 < 1.0 and isinstance(SimulatorHung("x"), SimulatorLost)
    t0 = time.monotonic()
    with pytest.raises(SimulatorHung, match="not asked to read: the connection was given up"):
        dog.call("read", 5.0, lambda: 1)
    assert time.monotonic() - t0 < 0.1


# -- a campaign against a server whose tick never returns -------------------------------------------------------
class HangingSimulation(LiteSimulation):
    """A lite episode whose server calls go through the connection's watchdog; on a hanging connection the
    tick of step 5 never returns."""

    def tick(self):  # noqa: ANN201
        b = self._backend
        if b.hangs and self._step == 5:
            b.watchdog.call(f"ticking (step {self._step})", HANG_DEADLINE_S, never_returns)
        return super().tick()


HANG_DEADLINE_S = 0.3


class HangingBackend(LiteBackend):
    """Connection 1 reaches a server that hangs; later connections (the campaign's retry) a working one."""

    connections = 0
    closed: list[int] = []

    def __init__(self) -> None:
        super().__init__()
        type(self).connections += 1
        self.number = type(self).connections
        self.hangs = self.number == 1
        self.watchdog = Watchdog(f"fake server (connection {self.number})")

    def create_simulation(self, scene, *, seed, weather=None, camera=None, render=True):  # noqa: ANN001, ANN201
        sim = super().create_simulation(scene, seed=seed, weather=weather, camera=camera, render=render)
        sim.__class__ = HangingSimulation
        return sim

    def close(self) -> None:
        type(self).closed.append(self.number)
        super().close()


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> str:
    from genesis_rl.sim.lite.scenes import generate_catalog

    path = tmp_path_factory.mktemp("cat") / "highway.json"
    generate_catalog("highway", 4, 0).save(path)
    return str(path)


def test_a_campaign_whose_server_hangs_marks_the_episode_lost_and_retries_it(tmp_path, catalog) -> None:
    from genesis_rl.campaigns.campaign import CampaignSpec, run_campaign

    spec = CampaignSpec(policies=("sunny",), catalog=catalog, scenes=1, seed=1, steps=20,
                        env={"system": "blind", "backend": f"{__name__}:HangingBackend"})
    folder = tmp_path / "eval"
    t0 = time.monotonic()
    with pytest.warns(UserWarning, match="simulator lost .*did not return within 0.3 s.* reconnecting, retry 1 of 2"):
        summary = run_campaign(spec, folder, progress=False)
    assert time.monotonic() - t0 < 60.0  # finished: the hung tick cost HANG_DEADLINE_S, not the campaign
    assert summary["policies"]["sunny"]["episodes"] == 1
    (row_path,) = (folder / "episodes" / "sunny").glob("*.json")
    row = json.loads(row_path.read_text())
    assert row["steps"] == 20 and len(row["simulator_lost"]) == 1
    assert "connection 1) stopped answering: ticking (step 5) did not return within 0.3 s" in row["simulator_lost"][0]
    assert HangingBackend.connections == 2 and HangingBackend.closed[0] == 1  # the lost one closed, a fresh one


# -- the CARLA backend after a hang -------------------------------------------------------------------------------
def test_a_carla_tick_that_never_returns_loses_the_episode_and_close_survives(monkeypatch) -> None:
    pytest.importorskip("carla")
    import test_carla_faults as fakes

    from genesis_rl.sim.carla import backend as backend_module
    from genesis_rl.sim.carla.backend import CarlaBackend
    from genesis_rl.sim.carla.connection import CarlaServerLost

    clients = []

    def connect(host, port, timeout, tm_port=None):  # noqa: ANN001, ANN202
        clients.append(fakes.FakeClient(fakes.TickingWorld({f: {10: 5.0, 11: 5.0} for f in range(100, 110)})))
        return clients[-1]

    class DeadTM(fakes.FakeTM):
        def shut_down(self) -> None:  # the real one's destructor calls the dead server: the process aborts
            raise AssertionError("shut_down called on a lost server's traffic manager")

    monkeypatch.setattr(backend_module, "connect", connect)
    monkeypatch.setattr(backend_module, "deadline_for", lambda timeout: 0.3)
    b = CarlaBackend("localhost", 2000, tm_port=fakes._free_tcp_port())
    b.client.get_trafficmanager = DeadTM
    sim = fakes._bare_simulation(b, b.client.world)
    b._live.add(sim)
    sim._tm, sim._original_settings = b.traffic_manager(), SimpleNamespace(synchronous_mode=False)
    sim._advance(0)
    assert sim.tick().step == 1
    b.client.world.tick = never_returns
    t0 = time.monotonic()
    with pytest.raises(CarlaServerLost, match="ticking \\(step 1\\) did not return within 0.3 s"):
        sim.tick()
    assert time.monotonic() - t0 < 2.0 and b.lost
    t0 = time.monotonic()
    with pytest.warns(RuntimeWarning, match="was given up .*actors and settings are left on it"):
        b.close()  # asks the lost server nothing, never shuts its traffic manager down
    assert time.monotonic() - t0 < 0.5
    again = CarlaBackend("localhost", 2000, tm_port=b.tm_port)  # the campaign's reconnect, in this process
    with pytest.warns(RuntimeWarning, match=f"port {b.tm_port} is held by the traffic manager of a lost server"):
        tm = again.traffic_manager()
    assert tm.port != b.tm_port and not again.lost
