"""Issue 38, build item 4: every number is checked where it enters, with its physical range.

Each loader's numeric fields are swept with 0, a negative, a subnormal (1e-320), 1e308, inf, nan and wrong
types (a string, a bool, a list). Every case either loads and is sane (finite, of a magnitude no later
arithmetic overflows, and a subnormal only where 0 is accepted too) or is a UserInputError naming the field;
never another exception. One test per loader gathers every failing case, so a run lists them all.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError

#: the sweep: (label, value)
HOSTILE: list[tuple[str, Any]] = [
    ("zero", 0), ("zero_float", 0.0), ("negative", -1.0), ("negative_int", -1), ("subnormal", 1e-320),
    ("huge", 1e308), ("inf", math.inf), ("minus_inf", -math.inf), ("nan", math.nan), ("string", "5"),
    ("bool", True), ("list", [1.0]),
]
#: JSON integers have no size limit: a 400-digit one overflows float()
HUGE_INT = 10**400
#: an accepted value above this (in magnitude) is not sane: a product of a few of them would leave float64
SANE_MAGNITUDE = 1e7


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 24 else f"{text[:12]}...({len(text)} chars)"


def _outcome(load: Callable[[Any], Any], value: Any) -> tuple[str, Any]:
    """("ok", result), ("refused", message) or ("crash", "ExcType: message")."""
    try:
        return "ok", load(value)
    except UserInputError as err:
        return "refused", str(err)
    except Exception as err:  # noqa: BLE001  (anything else is the bug this test looks for)
        return "crash", f"{type(err).__name__}: {err}"


def sweep(fields: Iterable[tuple[str, str, Callable[[Any], Any]]],
          values: list[tuple[str, Any]] = HOSTILE,
          sane: Callable[[str, Any, Any], str | None] | None = None) -> list[str]:
    """Every (field, value) case that neither loads sanely nor is refused naming the field.

    ``fields``: (name, needle the refusal must contain, load(value) -> result). ``sane(name, value, result)``
    returns a reason when an accepted value is not sane (None: sane)."""
    problems = []
    for name, needle, load in fields:
        accepted: dict[str, Any] = {}
        for label, value in values:
            kind, out = _outcome(load, value)
            if kind == "crash":
                problems.append(f"{name} = {label}: {out}")
            elif kind == "refused":
                if needle not in out:
                    problems.append(f"{name} = {label}: refused without naming {needle!r}: {out}")
            else:
                accepted[label] = value
                if isinstance(value, bool) or not isinstance(value, int | float):
                    problems.append(f"{name} = {label} ({_short(value)}): a wrong type was accepted")
                    continue
                if abs(value) > SANE_MAGNITUDE or not math.isfinite(value):  # (a huge int stops at the first)
                    problems.append(f"{name} = {label} ({_short(value)}): accepted")
                    continue
                why = sane(name, value, out) if sane else None
                if why:
                    problems.append(f"{name} = {label} ({_short(value)}): accepted but {why}")
        if "subnormal" in accepted and "zero" not in accepted and "zero_float" not in accepted:
            problems.append(f"{name} = 1e-320 accepted where 0 is refused: it divides or scales to inf or 0")
    return problems


# -- catalogs ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def catalog_json() -> dict:
    from genesis_rl.sim.lite.scenes import generate_catalog

    return generate_catalog("highway", 1, 0).to_json()


def _catalog_fields(good: dict) -> list[tuple[str, str, Callable[[Any], Any]]]:
    from genesis_rl.sim.backends import catalog_from_json

    def setter(path: list[Any]) -> Callable[[Any], Any]:
        def load(value: Any) -> Any:
            data = json.loads(json.dumps(good))
            target = data
            for key in path[:-1]:
                target = target[key]
            target[path[-1]] = value
            return catalog_from_json(data)
        return load

    out = [("catalog.seed", "'catalog.seed'", setter(["seed"])),
           ("scenes[0].seed", "'scenes[0].seed'", setter(["scenes", 0, "seed"])),
           ("scenes[0].index", "'scenes[0].index'", setter(["scenes", 0, "index"])),
           ("scenes[0].signal_offset", "'scenes[0].signal_offset'", setter(["scenes", 0, "signal_offset"]))]
    for j in (0, 1):  # the ego and the lead
        v = f"scenes[0].vehicles[{j}]"
        for key in ("speed", "x", "y", "s", "yaw", "lane", "next_lane"):
            # a pose that disagrees with its lane is refused naming the vehicle's x/y: the vehicle is named
            out.append((f"{v}.{key}", v, setter(["scenes", 0, "vehicles", j, key])))
    for key in ("target_speed", "time_gap", "min_gap", "max_accel", "comfort_decel", "stop_rate", "speed_noise"):
        field = f"scenes[0].vehicles[1].autopilot.{key}"
        out.append((field, f"'{field}'", setter(["scenes", 0, "vehicles", 1, "autopilot", key])))
    return out


def test_every_catalog_number_is_checked_at_load(catalog_json) -> None:
    """A speed of 1000 m/s, 1e200 m/s (OverflowError in drive, evaluate, replay) or a max_accel of 1e308
    (a Panda3D assertion) was accepted; every catalog number now has a physical range."""
    problems = sweep(_catalog_fields(catalog_json), [*HOSTILE, ("huge_int", HUGE_INT), ("fast", 1000.0),
                                                     ("overflowing", 1e200)])
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(("path", "value", "message"), [
    (["scenes", 0, "vehicles", 0, "speed"], 1e200,
     r"'scenes\[0\]\.vehicles\[0\]\.speed' = 1e\+200; expected <= 70 m/s \(allowed for the ego: 0\.\.70 m/s\)"),
    (["scenes", 0, "vehicles", 1, "speed"], 1000.0, r"vehicles\[1\]\.speed' = 1000\.0; expected <= 70 m/s"),
    (["scenes", 0, "vehicles", 1, "autopilot", "max_accel"], 1e308,
     r"autopilot\.max_accel' = 1e\+308; expected <= 15 m/s\^2 \(allowed for the lead"),
    (["scenes", 0, "vehicles", 1, "speed"], HUGE_INT, r"vehicles\[1\]\.speed' = 100000000000\.\.\.; expected <="),
])
def test_absurd_catalog_numbers_are_refused_naming_field_unit_and_range(catalog_json, path, value, message) -> None:
    from genesis_rl.sim.backends import catalog_from_json

    data = json.loads(json.dumps(catalog_json))
    target = data
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    with pytest.raises(UserInputError, match=message):
        catalog_from_json(data)


def test_a_catalog_at_the_ends_of_its_ranges_simulates_without_overflow(catalog_json) -> None:
    """The ranges are not only refusals: a scene whose every number sits at an end of its range (70 m/s,
    1e-3 or 15 m/s^2, a day's signal offset) simulates 300 steps with no float overflow or invalid value."""
    from genesis_rl.sim.backends import catalog_from_json
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.traffic import AutopilotParams, Traffic
    from genesis_rl.world.scenes.catalog import AUTOPILOT_RANGES

    for end in (0, 1):
        data = json.loads(json.dumps(catalog_json))
        for v in data["scenes"][0]["vehicles"]:
            v["speed"] = 70.0 if end else 0.0
            if v["autopilot"] is not None:
                v["autopilot"] = {k: (r.high if (i + end) % 2 else r.low) for i, (k, r) in
                                  enumerate(AUTOPILOT_RANGES.items())}
        data["scenes"][0]["signal_offset"] = 86_400.0 if end else -86_400.0
        scene = catalog_from_json(data).scenes[0]
        vs = scene.vehicles
        traffic = Traffic(load_map(scene.map), [v.make for v in vs], [v.lane for v in vs], [v.s for v in vs],
                          [v.speed for v in vs], [AutopilotParams(**v.autopilot) if v.autopilot else None for v in vs],
                          [v.next_lane for v in vs], np.random.default_rng(0), 0.05)
        traffic.time = scene.signal_offset
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            for k in range(300):
                traffic.step(k)
        assert np.isfinite(traffic.x).all() and np.isfinite(traffic.v).all()
        assert float(traffic.v.max()) < 80.0  # no vehicle left its make's powertrain far behind


def test_a_scene_with_only_the_ego_runs(catalog_json) -> None:
    """A structurally valid scene with the ego alone ended in a numpy casting error (the autopilot arrays
    were built as integers); it now simulates like any other (the lite simulation without its camera: the
    error was in the traffic, and rendering one vehicle is what every scene does)."""
    from genesis_rl.sim.backends import catalog_from_json
    from genesis_rl.sim.interface import VehicleControl
    from genesis_rl.sim.lite.backend import LiteBackend

    data = json.loads(json.dumps(catalog_json))
    data["scenes"][0]["vehicles"] = data["scenes"][0]["vehicles"][:1]
    scene = catalog_from_json(data).scenes[0]
    with LiteBackend() as backend, backend.create_simulation(scene, seed=0, render=False) as sim:
        sim.apply_ego_control(VehicleControl(throttle=0.6))
        ticks = [sim.tick() for _ in range(100)]
        (ego,) = sim.actors()
        assert sim.lead() is None or not sim.lead().present  # type: ignore[union-attr]
    assert not any(t.collisions for t in ticks)
    assert math.isfinite(ego.x) and 5.0 < ego.speed < 70.0  # it drove: 5 s at 0.6 throttle


# -- rulebooks and reward weights -------------------------------------------------------------------------------
def test_every_rulebook_parameter_is_checked() -> None:
    """A deceleration of 1e-320 made the RSS deficit inf ("damaged" loops); each parameter of the built-in
    rules now has a physical range, and an accepted one keeps every rule term finite."""
    from genesis_rl.loop.rules.rulebook import build_rulebook
    from genesis_rl.world.step_record import synthetic_step

    worst = [synthetic_step(ego_speed=70.0, lead_gap=0.01, lead_speed=0.0),
             synthetic_step(ego_speed=70.0, lead_gap=1e-9, lead_speed=0.0, collision=True, collision_speed=70.0)]

    def field(rule: str, key: str) -> tuple[str, str, Callable[[Any], Any]]:
        def load(value: Any) -> Any:
            return build_rulebook([{"name": rule, "params": {key: value}}], "rules.toml")
        return f"{rule}.{key}", f"{rule}.{key}", load

    def sane(name: str, value: Any, rulebook: Any) -> str | None:
        terms = [t for r in worst for t in rulebook.step_terms(r).values()]
        return None if all(math.isfinite(t) and t < 1e9 for t in terms) else f"a rule term is {terms}"

    fields = [field("proximity", "distance"), field("rss_deficit", "decel"),
              field("speed_for_visibility", "reaction_s"), field("speed_for_visibility", "decel")]
    problems = sweep(fields, [*HOSTILE, ("tiny", 1e-9), ("huge_int", HUGE_INT)], sane)
    assert not problems, "\n".join(problems)


def test_a_plugin_rule_parameter_without_a_range_is_bounded(monkeypatch) -> None:
    """A rule of one's own declares no range: its parameters must be 0 or of a magnitude in 1e-9..1e9."""
    from genesis_rl.loop.rules import rulebook as rb

    class Headway(rb.Rule):
        name = "headway_test"
        seconds: float = 2.0

        def term(self, record: Any) -> float:
            return 0.0

    monkeypatch.setitem(rb.RULES, "headway_test", rb._as_rule_class(Headway, "test"))
    assert rb.build_rulebook([{"name": "headway_test", "params": {"seconds": 0.0}}]).rules[0].params() == \
        {"seconds": 0.0}
    for bad in (1e-320, 1e308, 1e10):
        with pytest.raises(UserInputError, match=re.escape(f"headway_test.seconds = {bad!r} must be")):
            rb.build_rulebook([{"name": "headway_test", "params": {"seconds": bad}}], "r")


def test_a_rulebook_file_with_a_subnormal_deceleration_names_file_and_field(tmp_path) -> None:
    from genesis_rl.loop.rules.rulebook import load_rulebook

    path = tmp_path / "rules.toml"
    path.write_text('[[rules]]\nname = "rss_deficit"\nparams = { decel = 1e-320 }\n')
    with pytest.raises(UserInputError, match=r"rules\.toml.*rss_deficit\.decel = 1e-320 must be in 0\.1\.\.30 "
                                             r"m/s\^2"):
        load_rulebook(path)


def test_every_reward_weight_is_checked() -> None:
    """Reward weights of 1e308 turned the reward into inf (a torch ValueError in training)."""
    from genesis_rl.core.config import from_mapping
    from genesis_rl.loop.rules.reward import PaperReward, RewardConfig

    def field(key: str, rule: str | None = None) -> tuple[str, str, Callable[[Any], Any]]:
        def load(value: Any) -> Any:
            data = {"rule_weights": {rule: value}} if rule else {key: value}
            return from_mapping(RewardConfig, data, "env.reward")
        return (f"rule_weights.{rule}" if rule else key), (f"rule_weights.{rule}" if rule else key), load

    def sane(name: str, value: Any, config: Any) -> str | None:
        terms = PaperReward(config).terms(0.0, {"collision": 70.0, "proximity": 70.0, "rss_deficit": 1000.0},
                                          surprise=-1e6)
        return None if all(math.isfinite(t) for t in terms.values()) else f"the reward is {terms}"

    fields = [field(k) for k in ("collision_weight", "proximity_weight", "iou_weight", "naturalness_weight")]
    problems = sweep([*fields, field("", "rss_deficit")], sane=sane)
    assert not problems, "\n".join(problems)


# -- knobs, env and training configs ---------------------------------------------------------------------------
def test_the_knob_step_fraction_is_checked() -> None:
    """A step fraction of 1e-320 froze the agent: a knob moved 1e-318 of its range per step."""
    from genesis_rl.world.knobs import KnobActionMapper, Weather

    def sane(name: str, value: Any, mapper: Any) -> str | None:
        before = Weather.default()
        after = mapper.apply(before, np.ones(mapper.action_dim))
        moved = abs(after["fog_density"] - before["fog_density"])
        return None if moved >= 0.05 else f"fog moves {moved} % per step: the agent is frozen"

    fields = [("max_step_fraction", "max_step_fraction",
               lambda v: KnobActionMapper(max_step_fraction=v))]
    problems = sweep(fields, [*HOSTILE, ("tiny", 1e-9), ("paper", 0.05)], sane)
    assert not problems, "\n".join(problems)


def _config_fields(cls: type, section: str, keys: Iterable[str]) -> list[tuple[str, str, Callable[[Any], Any]]]:
    from genesis_rl.core.config import from_mapping

    def field(key: str) -> tuple[str, str, Callable[[Any], Any]]:
        return f"{section}.{key}", f"{section}.{key}", lambda v: from_mapping(cls, {key: v}, section)

    return [field(k) for k in keys]


def test_every_env_number_is_checked() -> None:
    """Camera sizes, episode steps, seeds, spreads, ports and the CARLA timeout (inf became 0 s) of [env]."""
    from genesis_rl.env.genesis_env import EnvConfig

    keys = ["scenes", "catalog_seed", "max_step_fraction", "start_spread", "episode_steps", "camera_width",
            "camera_height", "obs_width", "obs_height", "obs_history", "carla_port", "carla_tm_port",
            "carla_timeout"]
    problems = sweep(_config_fields(EnvConfig, "env", keys), [*HOSTILE, ("port_70000", 70000)])
    assert not problems, "\n".join(problems)


def test_every_training_number_is_checked() -> None:
    """Learning rates, discounts, sizes and counts of [ppo], [sac] and [train]."""
    from genesis_rl.training.config import PPOConfig, SACConfig, TrainConfig

    fields = [*_config_fields(PPOConfig, "ppo", ["learning_rate", "n_steps", "batch_size", "n_epochs", "gamma",
                                                 "gae_lambda", "clip_range", "ent_coef", "vf_coef",
                                                 "max_grad_norm", "log_std_init"]),
              *_config_fields(SACConfig, "sac", ["learning_rate", "buffer_size", "learning_starts", "batch_size",
                                                 "tau", "gamma", "train_freq", "gradient_steps"]),
              *_config_fields(TrainConfig, "train", ["total_timesteps", "envs", "seed", "checkpoint_every",
                                                     "torch_threads"])]
    problems = sweep(fields)
    from genesis_rl.core.config import from_mapping

    for text in ("inf", "auto_inf", "1e308", "auto_1e-320", "nan"):  # SAC's entropy coefficient is a string
        kind, out = _outcome(lambda v: from_mapping(SACConfig, {"ent_coef": v}, "sac"), text)
        if kind != "refused" or "sac.ent_coef" not in out:
            problems.append(f"sac.ent_coef = {text!r}: {kind} {out}")
    for arch in ([64, 10**12], [64] * 1000, [True, 64]):
        kind, out = _outcome(lambda v: from_mapping(SACConfig, {"net_arch": v}, "sac"), arch)
        if kind != "refused" or "sac.net_arch" not in out:
            problems.append(f"sac.net_arch = {arch[:3]}...: {kind} {out}")
    assert not problems, "\n".join(problems)


def test_a_bad_number_in_a_config_file_names_the_key(tmp_path) -> None:
    from genesis_rl.training.config import load_run_config

    path = tmp_path / "c.toml"
    path.write_text("[env]\nmax_step_fraction = 1e-320\n")
    with pytest.raises(UserInputError, match=r"env\.max_step_fraction = 1e-320 must be in 0\.001\.\.1"):
        load_run_config(path)
    path.write_text("[env.reward]\ncollision_weight = 1e308\n")
    with pytest.raises(UserInputError, match=r"env\.reward\.collision_weight = 1e\+308 must be in 0\.\.1e\+06"):
        load_run_config(path)
    path.write_text("[env]\ncarla_timeout = inf\n")
    with pytest.raises(UserInputError, match=r"env\.carla_timeout = inf must be in 0\.1\.\.3600 s"):
        load_run_config(path)


# -- ODD files -------------------------------------------------------------------------------------------------
def test_every_odd_bound_is_checked() -> None:
    from genesis_rl.world.odd.conditions import conditions_model
    from genesis_rl.world.odd.domain import parse_odd

    lite = conditions_model("lite")

    def field(quantity: str, end: str, unit: str) -> tuple[str, str, Callable[[Any], Any]]:
        def load(value: Any) -> Any:
            return parse_odd({quantity: {end: value, "unit": unit}}, "odd.toml", lite)
        return f"{quantity}.{end}", quantity, load

    fields = [field("visibility", "min", "m"), field("visibility", "max", "m"), field("rain_rate", "min", "mm/h"),
              field("rain_rate", "max", "mm/h"),
              ("boundary_margin", "boundary_margin", lambda v: parse_odd({"boundary_margin": v}, "odd.toml", lite))]
    problems = sweep(fields, [*HOSTILE, ("far", 1e9)])
    assert not problems, "\n".join(problems)


# -- detector weights ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def checkpoint() -> dict:
    from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS, load_checkpoint

    return load_checkpoint(DEFAULT_WEIGHTS)


def _save(ckpt: dict, path: Path, **changes: Any) -> Path:
    import torch

    torch.save({**ckpt, **changes}, path)
    return path


@pytest.mark.parametrize("poison", ["nan", "inf", "huge", "negative_variance"])
def test_damaged_detector_weights_are_refused_naming_the_file(checkpoint, tmp_path, poison) -> None:
    """Weights that are all NaN ran with IoU 0 and no word: every result measured a broken detector."""
    import torch

    from genesis_rl.sut.perception.detector import VehicleDetector

    state = {k: v.clone() for k, v in checkpoint["state_dict"].items()}
    if poison == "negative_variance":
        key = next(k for k in state if k.endswith("running_var"))
        state[key] = -state[key]
    else:
        for k, v in state.items():
            if v.is_floating_point():
                state[k] = torch.full_like(v, {"nan": math.nan, "inf": math.inf, "huge": 1e30}[poison])
    path = _save(checkpoint, tmp_path / f"{poison}.pt", state_dict=state)
    with pytest.raises(UserInputError, match=rf"weights file {path}: tensor '.*' .*damaged"):
        VehicleDetector(path)


def test_a_detector_checkpoint_s_numbers_are_checked(checkpoint, tmp_path) -> None:
    from genesis_rl.sut.perception.detector import VehicleDetector

    problems = []
    for label, value in HOSTILE:
        path = _save(checkpoint, tmp_path / f"t_{label}.pt", score_threshold=value)
        kind, out = _outcome(VehicleDetector, path)
        if kind != "refused" or "score_threshold" not in out or str(path) not in out:
            problems.append(f"score_threshold = {label}: {kind} {out}")
    for label, cfg in (("huge_channels", {"channels": [16, 24, 32, 48, 10**9]}),
                       ("inf_channels", {"channels": [16, 24, 32, 48, math.inf]}),
                       ("huge_input", {"input_width": 320 * 10**6})):
        path = _save(checkpoint, tmp_path / f"c_{label}.pt", model_config={**checkpoint["model_config"], **cfg})
        kind, out = _outcome(VehicleDetector, path)
        if kind != "refused" or str(path) not in out:
            problems.append(f"model_config {label}: {kind} {out}")
    assert not problems, "\n".join(problems)


# -- command-line flags ----------------------------------------------------------------------------------------
def test_carla_timeout_and_ports_are_checked_by_the_parser() -> None:
    """--carla-timeout inf became 0 s in the client; --carla-tm-port 70000 was not checked."""
    from genesis_rl.sim.backends import add_backend_arguments

    parser = argparse.ArgumentParser(exit_on_error=False)
    add_backend_arguments(parser)
    problems = []
    for flag, good, bads in (
        ("--carla-timeout", "10", ["inf", "nan", "0", "-1", "1e-320", "1e308", "ten", ""]),
        ("--carla-tm-port", "8000", ["70000", "0", "-1", "1e3", "x", "65536"]),
        ("--carla-port", "2000", ["70000", "0", "-1"]),
    ):
        parser.parse_args([flag, good])
        for bad in bads:
            try:
                parser.parse_args([flag, bad])
                problems.append(f"{flag} {bad!r} accepted")
            except argparse.ArgumentError:
                pass
            except Exception as err:  # noqa: BLE001
                problems.append(f"{flag} {bad!r}: {type(err).__name__}: {err}")
    assert parser.parse_args(["--carla-timeout", "0.5"]).carla_timeout == 0.5
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(("argv", "needle"), [
    (["drive", "--backend", "carla", "--carla-timeout", "inf"], "--carla-timeout: 'inf'"),
    (["drive", "--backend", "carla", "--carla-tm-port", "70000"], "--carla-tm-port: '70000'"),
    (["drive", "--threads", "100000"], "--threads = 100,000, over the limit of 256 threads"),  # was a segfault in torch
])
def test_the_cli_refuses_a_bad_connection_number_in_one_line(tmp_path, argv, needle) -> None:
    """Exit 2 with one error line naming the flag (argparse's usage line comes first), never a traceback."""
    r = subprocess.run([sys.executable, "-m", "genesis_rl", *argv, "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    errors = [line for line in r.stderr.splitlines() if "error:" in line]
    assert r.returncode == 2 and len(errors) == 1 and needle in errors[0], r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "o").exists()


def test_the_cli_refuses_an_absurd_catalog_speed_in_one_line(catalog_json, tmp_path) -> None:
    data = json.loads(json.dumps(catalog_json))
    data["scenes"][0]["vehicles"][0]["speed"] = 1e200
    path = tmp_path / "c.json"
    path.write_text(json.dumps(data))
    r = subprocess.run([sys.executable, "-m", "genesis_rl", "drive", "--catalog", str(path), "--steps", "5",
                        "--no-gif", "--quiet", "--out", str(tmp_path / "o")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "'scenes[0].vehicles[0].speed' = 1e+200; expected <= 70 m/s" in r.stderr


def test_a_recorded_weather_is_checked_like_a_typed_one() -> None:
    """Records and telemetry are files too: a knob value of 1e308, -5 %, a bool, a list or a 400-digit
    integer steered the simulator as it was (or raised a TypeError/OverflowError)."""
    from genesis_rl.world.knobs import Weather

    def sane(name: str, value: Any, weather: Any) -> str | None:
        return None if 0.0 <= weather["fog_density"] <= 100.0 else f"fog_density is {weather['fog_density']}"

    fields = [("fog_density", "fog_density", lambda v: Weather.from_recorded({"fog_density": v}))]
    problems = sweep(fields, [*HOSTILE, ("huge_int", HUGE_INT), ("above", 100.5)], sane)
    problems = [p for p in problems if "string" not in p]  # telemetry CSV cells are strings: '5' reads as 5
    assert not problems, "\n".join(problems)
    assert Weather.from_recorded({"fog_density": "12.5"})["fog_density"] == 12.5


def test_a_campaign_file_s_seeds_and_steps_are_checked(tmp_path) -> None:
    """campaign.json is shared between people: a negative episode seed reached numpy (a ValueError
    traceback on resume and report), a 400-digit one or 0 steps passed the integer check."""
    from genesis_rl.campaigns.campaign_files import CAMPAIGN_SCHEMA, CAMPAIGN_VERSION, read_campaign_meta

    def load(spec_seed: Any = 0, steps: Any = 512, pair: Any = (3, 17)) -> Any:
        meta = {"schema": CAMPAIGN_SCHEMA, "version": CAMPAIGN_VERSION, "spec": {"policies": ["sunny"],
                "seed": spec_seed, "steps": steps}, "scenes": [list(pair)]}
        (tmp_path / "campaign.json").write_text(json.dumps(meta))
        return read_campaign_meta(tmp_path)

    assert load()["scenes"] == [[3, 17]]
    problems = sweep([("spec.seed", "spec.seed", lambda v: load(spec_seed=v)),
                      ("spec.steps", "spec.steps", lambda v: load(steps=v)),
                      ("scenes[0][1]", "'scenes'", lambda v: load(pair=(3, v))),
                      ("scenes[0][0]", "'scenes'", lambda v: load(pair=(v, 17)))], [*HOSTILE, ("huge_int", HUGE_INT)])
    assert not problems, "\n".join(problems)


def test_every_controller_setting_is_checked() -> None:
    """env.system_kwargs.controller (a config file's) reached the built-in system's IDM unchecked: a
    comfort deceleration of 1e-320 or a max_accel of 1e308 drove it to inf."""
    from genesis_rl.sut.system.controller import ControllerConfig
    from genesis_rl.sut.system.protocol import load_system

    def field(key: str) -> tuple[str, str, Callable[[Any], Any]]:
        return f"controller.{key}", f"controller.{key}", lambda v: load_system("blind", controller={key: v})

    keys = [f for f in ControllerConfig.__dataclass_fields__]
    assert len(keys) >= 16
    problems = sweep([field(k) for k in keys])
    assert not problems, "\n".join(problems)
