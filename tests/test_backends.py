"""Backends are declared once (genesis_rl.sim.backends) and a backend from outside the package is named by its
import path, as systems and policies are."""

import json
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.commands.cli import build_parser, main
from genesis_rl.core.errors import UserInputError
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.sim.backends import BACKENDS, backend_class, catalog_from_json, load_catalog, make_backend
from genesis_rl.sim.interface import Backend
from genesis_rl.sim.lite.scenes import generate_catalog

PLUGINS = Path(__file__).parent / "plugins"
TICKLOG = "ticklog_backend:TickLogBackend"
STEPS = 12


@pytest.fixture
def plugins_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(PLUGINS))


def test_every_builtin_backend_is_a_backend_that_drives_its_own_catalogs():
    assert list(BACKENDS) == ["lite", "carla"]
    for name in BACKENDS:
        cls = backend_class(name)
        assert issubclass(cls, Backend) and cls.name == name and cls.catalog_kind == name
    assert (backend_class("lite").needs_catalog, backend_class("carla").needs_catalog) == (False, True)


def test_help_and_flag_list_the_registry():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    backend_help = next(a.help for a in sub.choices["drive"]._actions if a.dest == "backend")
    assert all(backend_help.count(f"{name} (") == 1 for name in BACKENDS) and "package.module:Class" in backend_help
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["drive", "--out", "x", "--backend", "unreal"])
    assert exc.value.code == 2


@pytest.mark.parametrize(("spec", "message"), [
    ("unreal", r"env.backend = 'unreal' is unknown; allowed: lite, carla or package.module:Class"),
    ("genesis_rl.no_such_module:X", r"env.backend 'genesis_rl.no_such_module:X': cannot import module 'genesis_rl"),
    ("ticklog_backend:Nope", r"env.backend 'ticklog_backend:Nope': module 'ticklog_backend' has no class 'Nope'"),
    ("genesis_rl.world.knobs:KnobSpec", r"class KnobSpec is not a genesis_rl.sim.interface.Backend subclass"),
    ("carla", r"env.backend = 'carla' needs env.catalog: a catalog made with genesis-rl scenes --backend carla"),
])
def test_bad_backend_settings_are_named(plugins_on_path, spec, message):
    with pytest.raises(UserInputError, match=message):
        EnvConfig(backend=spec)


def _episode(backend: str) -> tuple[GenesisEnv, list[dict]]:
    env = GenesisEnv(EnvConfig(backend=backend, system="oracle", scenes=3, catalog_seed=4, episode_steps=STEPS,
                               camera_width=96, camera_height=72, obs_width=48, obs_height=36))
    env.reset(seed=1, options={"scene": 2})
    infos = []
    for _ in range(STEPS):
        infos.append(env.step(np.full(env.action_space.shape, 0.5, np.float32))[4])
    return env, infos


@pytest.mark.render
def test_a_backend_from_outside_the_package_runs_an_episode(plugins_on_path):
    env, infos = _episode(TICKLOG)
    try:
        assert type(env.backend).__name__ == "TickLogBackend" and env.backend.name == "ticklog"
        ticks = env.backend.ticks
        # one tick per env step, in order, on the scene asked for, seen by the env as the backend logged it
        assert [(t.scene, t.step) for t in ticks] == [(2, k) for k in range(1, STEPS + 1)]
        assert [t.ego_speed for t in ticks] == [i["ego_speed"] for i in infos]
        assert ticks[-1].ego_speed > 1.0  # the ego drove: this is a real simulation, not a stub
    finally:
        env.close()
    lite, lite_infos = _episode("lite")
    lite.close()
    # it is lite underneath: the same seeds give the same episode, step for step
    assert [i["reward"] for i in infos] == [i["reward"] for i in lite_infos]
    assert [i["ego_speed"] for i in infos] == [i["ego_speed"] for i in lite_infos]


def test_a_plugin_backend_makes_the_catalogs_of_its_kind(plugins_on_path, tmp_path, capsys):
    out = tmp_path / "s.json"
    assert main(["scenes", "--backend", TICKLOG, "--map", "highway", "--count", "2", "--seed", "5",
                 "--out", str(out), "--quiet"]) == 0
    line = json.loads(capsys.readouterr().out)
    assert (line["scenes"], line["map"]) == (2, "highway")
    # a TickLogBackend drives lite catalogs: the same scenes lite makes, checked on load as lite's
    assert load_catalog(out).to_json() == generate_catalog("highway", 2, 5).to_json()


def test_catalog_checks_follow_the_catalogs_backend():
    lite = json.loads(json.dumps(generate_catalog("urban", 1, 0).to_json()))
    lite["scenes"][0]["vehicles"][0]["x"] += 50.0  # off its lane: lite refuses it
    with pytest.raises(UserInputError, match=r"vehicles\[0\]\.x'/'y'.*m from lane"):
        catalog_from_json(lite)
    lite["backend"] = "carla"  # the same poses as a CARLA catalog: snapped to the server's lanes at spawn
    assert catalog_from_json(lite).backend == "carla"


def test_make_backend_builds_by_name_and_by_import_path(plugins_on_path):
    with make_backend("lite") as b:
        assert type(b).__name__ == "LiteBackend"
    with make_backend(TICKLOG) as b:
        assert b.name == "ticklog" and b.ticks == []
