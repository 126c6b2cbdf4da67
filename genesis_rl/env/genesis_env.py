"""``GenesisEnv``: the agent turns the weather knobs while the system under test drives.

Step template (fixed): action -> knob deltas (at most ``max_step_fraction`` of each range) -> simulator
tick -> sensors -> system under test -> rulebook -> reward -> terminated/truncated -> info. Each reset
samples a scene from the catalog with the env's seeded generator, so ``reset(seed=s)`` replays an episode.
The observation is the ego camera's RGB frame (downscaled for the policy), optionally with the knob vector.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from typing import Any

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from genesis_rl.core import limits, ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.plugins import check_import, gate_held, import_modules
from genesis_rl.core.state_copy import copy_state
from genesis_rl.env.observation import (
    FEATURE_OBSERVATIONS,
    NEIGHBOUR_FEATURES,
    OBSERVATIONS,
    FeatureHistory,
    actor_feature_names,
    observation_space,
    step_features,
)
from genesis_rl.env.snapshot import EnvSnapshot
from genesis_rl.loop.drive import ClosedLoop
from genesis_rl.loop.frames import annotate_frame
from genesis_rl.loop.rules.reward import RewardConfig, make_reward
from genesis_rl.loop.rules.rulebook import Rulebook, check_rulebook_imports, rulebook_for
from genesis_rl.sim.backends import backend_class, catalog_or_generate, check_backend_setting, make_backend
from genesis_rl.sim.interface import (
    EXPOSURE_JITTER_MAX,
    FIXED_DELTA_SECONDS,
    ActorEvent,
    CameraConfig,
    ConnectionSettings,
    Simulation,
)
from genesis_rl.sut.system.protocol import BUILTIN_SYSTEMS, load_system
from genesis_rl.world.knobs import KNOBS, PAPER_KNOBS, KnobActionMapper, Weather, parse_weather
from genesis_rl.world.odd.conditions import conditions_model
from genesis_rl.world.odd.domain import ODD, check_start, load_odd
from genesis_rl.world.odd.dynamics import DYNAMICS, WeatherModel, max_deltas
from genesis_rl.world.step_record import StepRecord

ENV_ID = "genesis_rl/Weather-v0"


#: the physical range of every numeric [env] key (the knob step fraction is checked by KnobActionMapper)
ENV_RANGES: dict[str, ranges.Ranged] = {
    "scenes": ranges.Ranged(1, 2**31 - 1, "scenes", integer=True),  # and at most limits.SCENES
    "catalog_seed": ranges.SEED,  # numpy refuses negative seeds, with a traceback
    "start_spread": ranges.Ranged(0.0, 1.0, note="0: start_weather"),
    "start_bonus": ranges.Ranged(0.0, 1e6, note="0: none"),
    "start_bonus_cells": ranges.Ranged(2, 64, "cells", integer=True),
    "episode_steps": ranges.Ranged(1, 2**31 - 1, "steps", integer=True),  # and at most limits.SIM_STEPS
    "camera_width": ranges.Ranged(16, 4096, "px", integer=True),
    "camera_height": ranges.Ranged(16, 4096, "px", integer=True),
    "camera_exposure_jitter": ranges.Ranged(0.0, EXPOSURE_JITTER_MAX, note="0: none"),
    "obs_width": ranges.Ranged(36, 1024, "px", integer=True, note="CNN policies need >= 36"),
    "obs_height": ranges.Ranged(36, 1024, "px", integer=True, note="CNN policies need >= 36"),
    "obs_history": ranges.Ranged(1, 16, "steps", integer=True),
    "carla_port": ranges.PORT,
    "carla_tm_port": ranges.PORT,
    "carla_timeout": ranges.TIMEOUT,
}
#: keys of ENV_RANGES that may be None (carla_tm_port: carla_port + 6000)
OPTIONAL_RANGED = frozenset({"carla_tm_port"})


#: how the start head's action names a held knob's start (``EnvConfig.start_action``)
START_ACTIONS = ("relative", "absolute")


@dataclass(frozen=True)
class EnvConfig:
    """Every setting of the environment, with units; defaults are the paper's where it has one."""

    map: str = "urban"  # lite map of generated scenes (when no catalog is given)
    catalog: str | None = None  # scene catalog file; None: generate `scenes` scenes with `catalog_seed`
    scenes: int = 1202  # catalog size when generating (the paper's Town10 count)
    catalog_seed: int = 0
    system: str = "builtin"  # system under test: builtin, blind, oracle, yolo or package.module:Class
    system_kwargs: dict[str, Any] = field(default_factory=dict)
    plugins: tuple[str, ...] = ()  # modules imported first: they register knobs, rules (docs/extending.md)
    knobs: tuple[str, ...] = PAPER_KNOBS  # the knobs the agent turns (action dimensions, in order)
    disabled_knobs: tuple[str, ...] = ()  # ablation: these stay at their starting value
    max_step_fraction: float = 0.05  # naturalness limit: largest change per step, as a fraction of range
    dynamics: str = "paper"  # paper: max_step_fraction per step; natural: outdoor rates per second (docs/odd.md)
    odd: str | None = None  # operational design domain file (configs/odd/*.toml): steps are labelled against it
    odd_keep_inside: bool = True  # and policies are kept inside it (false: label only, e.g. to audit old runs)
    start_weather: str = "clear_noon"  # preset and/or KNOB=VALUE list
    start_spread: float = 0.0  # training only (exploring starts): each knob the agent turns starts at a random
    #                            point up to this fraction of what it can move in an episode away from
    #                            start_weather, inside the ODD; drawn from the episode seed. 0: start_weather
    start_head: bool = False  # the agent's first action of an episode chooses where the held knobs start (the
    #                          sun: its altitude, and its azimuth relative to the ego's heading), as a search
    #                          chooses its start; that step is not simulated. Needs a features observation
    start_action: str = "relative"  # how the start head's action names a held knob's start: relative (0 keeps
    #                                 the episode's drawn start, -1/+1 the knob's ends) or absolute (-1..+1 spans
    #                                 the knob's range whatever the draw: one action, one sun altitude). The
    #                                 sun's azimuth is its bearing from the ego's heading either way
    start_bonus: float = 0.0  # training only: a count bonus for the start head, start_bonus / sqrt(n) added to
    #                           the first tick's reward, n the starts this env chose in the same cell of the
    #                           held knobs' actions (start_bonus_cells a knob), so that rarely tried starts are
    #                           tried (exploration aimed at novelty; docs/zoo.md). 0: none
    start_bonus_cells: int = 8  # cells per held knob's action for start_bonus
    start_bonus_knobs: tuple[str, ...] = ()  # the held knobs whose cells start_bonus counts (empty: every held
    #                                          knob; a few, as the sun's two, keep the cells few enough to revisit)
    episode_steps: int = 512  # steps per episode (0.05 s each), then truncated
    camera_width: int = 320  # the system's camera [px]
    camera_height: int = 240
    #: frame-to-frame exposure jitter of the camera (log-sd of each frame's gain, drawn from the world seed; 0:
    #: none, as every preset; 0.03 is a gain a few per cent off from frame to frame), lite only
    camera_exposure_jitter: float = 0.0
    obs_width: int = 96  # the policy's image [px] (the paper's 640x480, downscaled; 4:3 as the camera)
    obs_height: int = 72
    obs_knobs: bool = False  # observe {"image", "knobs"} instead of the image alone (= observation "image+knobs")
    observation: str = "image"  # image (the paper's), image+knobs, features, image+features (env/observation.py)
    obs_history: int = 4  # feature vectors stacked in the features observations (the last N steps)
    rulebook: str | None = None  # TOML rulebook; None: collision, proximity (5 m), rss_deficit (5 m/s^2), and
    #                              speed_for_visibility when an ODD is declared
    reward: RewardConfig = field(default_factory=RewardConfig)
    terminate_on_collision: bool = False  # the paper runs every episode for its full length
    backend: str = "lite"  # simulator: a name in genesis_rl.sim.backends.BACKENDS (lite, carla) or package.module:Class
    carla_host: str = "localhost"
    carla_port: int = 2000  # RPC port
    carla_tm_port: int | None = None  # traffic manager port; None: carla_port + 6000 (one per run)
    carla_timeout: float = 10.0  # [s] per client call

    def __post_init__(self) -> None:
        import_modules(self.plugins, "env.plugins")  # before the knob checks below
        for k, rng in ENV_RANGES.items():  # an int or a number before the comparisons below
            if getattr(self, k) is not None or k not in OPTIONAL_RANGED:
                ranges.check_type(getattr(self, k), f"env.{k}", rng)
        if self.system not in BUILTIN_SYSTEMS and ":" in self.system:  # refused here, before env processes start
            check_import(self.system.partition(":")[0], f"env.system '{self.system}'")
        if self.rulebook is not None and gate_held():
            check_rulebook_imports(self.rulebook)
        if self.episode_steps < 1:
            raise UserInputError(f"env.episode_steps = {self.episode_steps} must be >= 1")
        limits.SIM_STEPS.check(self.episode_steps, "env.episode_steps")  # corners/train --steps 10**12: years
        for k in ("obs_width", "obs_height"):
            if not 36 <= getattr(self, k) <= 1024:
                raise UserInputError(f"env.{k} = {getattr(self, k)} must be in 36..1024 (CNN policies need >= 36)")
        if self.scenes < 1:
            raise UserInputError(f"env.scenes = {self.scenes} must be >= 1")
        limits.SCENES.check(self.scenes, "env.scenes")
        if self.observation not in OBSERVATIONS:
            raise UserInputError(f"env.observation = '{self.observation}'; allowed: {', '.join(OBSERVATIONS)}")
        if self.obs_knobs and self.observation not in ("image", "image+knobs"):
            raise UserInputError(f"env.obs_knobs = true and env.observation = '{self.observation}' disagree; "
                                 "leave obs_knobs out (observation 'image+knobs' is what it meant)")
        if not 1 <= self.obs_history <= 16:
            raise UserInputError(f"env.obs_history = {self.obs_history} must be in 1..16")
        if self.catalog_seed < 0:  # numpy refuses negative seeds, with a traceback
            raise UserInputError(f"env.catalog_seed = {self.catalog_seed}; allowed: an integer >= 0")
        for k in ("camera_width", "camera_height"):
            if not 16 <= getattr(self, k) <= 4096:
                raise UserInputError(f"env.{k} = {getattr(self, k)} must be in 16..4096")
        if self.camera_exposure_jitter and self.backend != "lite":
            raise UserInputError(f"env.camera_exposure_jitter = {self.camera_exposure_jitter} is lite's camera model; "
                                 f"env.backend = '{self.backend}' keeps its own exposure (CARLA: the RGB blueprint's "
                                 "exposure_mode): set it to 0")
        if set(self.disabled_knobs) >= set(self.knobs):
            raise UserInputError(f"env.disabled_knobs {list(self.disabled_knobs)} disable every knob the agent "
                                 f"turns ({', '.join(self.knobs)}); leave at least one")
        for k in ("carla_port", "carla_tm_port"):
            if getattr(self, k) is not None and not 1 <= getattr(self, k) <= 65535:
                raise UserInputError(f"env.{k} = {getattr(self, k)} must be a port in 1..65535")
        if not self.carla_timeout > 0:
            raise UserInputError(f"env.carla_timeout = {self.carla_timeout} must be > 0 [s]")
        KnobActionMapper(self.knobs, self.max_step_fraction, self.disabled_knobs)  # names, limits checked
        if self.dynamics not in DYNAMICS:
            raise UserInputError(f"env.dynamics = '{self.dynamics}' is unknown; allowed: {', '.join(DYNAMICS)}")
        if not 0.0 <= self.start_spread <= 1.0:
            raise UserInputError(f"env.start_spread = {self.start_spread} must be in 0..1 (0: start_weather)")
        if self.start_action not in START_ACTIONS:
            raise UserInputError(f"env.start_action = '{self.start_action}'; allowed: {', '.join(START_ACTIONS)}")
        unknown = [k for k in self.start_bonus_knobs if k not in self.knobs]
        if unknown:
            raise UserInputError(f"env.start_bonus_knobs: {unknown} are not among env.knobs; allowed: "
                                 f"{', '.join(self.knobs)}")
        if self.start_head and self.observation_mode not in FEATURE_OBSERVATIONS:
            raise UserInputError(f"env.start_head = true needs a features observation (env.observation = "
                                 f"{' or '.join(repr(m) for m in FEATURE_OBSERVATIONS)}), not "
                                 f"'{self.observation_mode}': the start step is told apart by a feature")
        for k, rng in ENV_RANGES.items():  # finite, in its physical range (docs/reliability.md)
            if getattr(self, k) is not None or k not in OPTIONAL_RANGED:
                rng.check(getattr(self, k), f"env.{k}")
        if self.start_bonus and not self.start_head:
            raise UserInputError("env.start_bonus needs env.start_head = true (it rewards the start head's choices)")
        start = parse_weather(self.start_weather)
        if self.odd is not None:
            odd = self.load_odd()
            try:
                check_start(odd, start, conditions_model(self.backend))
            except UserInputError as err:
                raise UserInputError(f"env.odd: {err}") from None
        backend_cls = backend_class(self.backend, "env.backend")
        unrealised = [k for k in self.knobs if KNOBS[k].is_actor and k not in backend_cls.actor_knobs]
        if unrealised:
            raise UserInputError(f"env.knobs: actor knob(s) {unrealised} are not realised by env.backend = "
                                 f"'{self.backend}'; it realises: {', '.join(backend_cls.actor_knobs) or 'none'} "
                                 "(docs/actors.md)")
        check_backend_setting(self.backend, self.catalog, "env.backend", "env.catalog")

    @property
    def observation_mode(self) -> str:
        """The observation mode, with the older ``obs_knobs = true`` read as 'image+knobs'."""
        return "image+knobs" if self.obs_knobs else self.observation

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def load_odd(self) -> ODD:
        assert self.odd is not None
        try:
            return load_odd(self.odd, conditions_model(self.backend))
        except UserInputError as err:
            raise UserInputError(f"env.odd: {err}") from None


def step_info(rec: StepRecord, knobs: dict[str, float]) -> dict[str, Any]:
    """``info`` of one step, a plain dict for Gymnasium users: the step's state, every rule term by rule name
    (``rules``) and every reward term."""
    return {
        "step": rec.step,
        "knobs": knobs,
        "ego_speed": rec.ego.speed,
        "lead_distance": rec.lead.true_distance,
        "lead_speed": rec.lead.speed,
        "perceived_lead_distance": rec.lead.perceived_distance,
        "n_detections": rec.perception.n_detections,
        "iou": rec.iou,
        "collision": rec.collision.collided,
        "rules": dict(rec.rules),
        **rec.reward,
    }


@contextmanager
def _setting(name: str) -> Iterator[None]:
    """Prefix a user error with the env setting it came from (``env.system: ...``), as config errors are."""
    try:
        yield
    except UserInputError as err:
        if str(err).startswith(name):
            raise
        raise UserInputError(f"{name}: {err}") from None


#: a knob whose reach over a whole episode is under this share of its range is set by the start alone
HELD_REACH = 0.01


class GenesisEnv(gym.Env):
    """Gymnasium env over a lite backend; see the module docstring for the step template."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, config: EnvConfig | None = None, render_mode: str | None = None, **overrides: Any) -> None:
        super().__init__()
        if overrides:
            unknown = set(overrides) - set(EnvConfig.field_names())
            if unknown:
                raise UserInputError(f"unknown env setting(s) {sorted(unknown)}; allowed: "
                                     f"{', '.join(EnvConfig.field_names())}")
            base = config or EnvConfig()
            config = EnvConfig(**{**{f: getattr(base, f) for f in EnvConfig.field_names()}, **overrides})
        self.config = c = config or EnvConfig()
        if render_mode not in (None, "rgb_array"):
            raise UserInputError(f"render_mode '{render_mode}' is not supported; allowed: rgb_array")
        self.render_mode = render_mode
        self.dt = FIXED_DELTA_SECONDS
        self.mapper = KnobActionMapper(c.knobs, c.max_step_fraction, c.disabled_knobs,
                                       max_delta=max_deltas(c.knobs, c.dynamics, self.dt, c.max_step_fraction))
        self.start_weather: Weather = parse_weather(c.start_weather)
        #: the declared domain (None: none), the backend's knob -> conditions map, the weather model
        self.odd: ODD | None = c.load_odd() if c.odd else None
        self.conditions_model = conditions_model(c.backend)
        self.weather_model = WeatherModel(tuple(c.knobs))
        with _setting("env.rulebook"):
            self.rulebook: Rulebook = rulebook_for(c.rulebook, with_odd=c.odd is not None)
        with _setting("env.reward"):
            self.reward_fn = make_reward(c.reward, self.rulebook, c.episode_steps, with_odd=c.odd is not None)
        with _setting("env.catalog" if c.catalog else "env.scenes"):
            self.catalog = catalog_or_generate(c.catalog, c.map, c.scenes, c.catalog_seed, map_field="env.map",
                                               backend=c.backend)


        self.camera = CameraConfig(width=c.camera_width, height=c.camera_height,
                                   exposure_jitter=c.camera_exposure_jitter)
        with _setting("env.system"):  # before the backend, so a bad system leaves no simulator open
            self.system = load_system(c.system, **c.system_kwargs)
        self.backend = make_backend(c.backend, ConnectionSettings(c.carla_host, c.carla_port, c.carla_tm_port,
                                                                  c.carla_timeout))

        #: actor knobs among the knobs: the features add what a tester measures of the actor (observation.py)
        self.actor_features = actor_feature_names(c.knobs)
        self.observation_space = observation_space(c.observation_mode, c.obs_height, c.obs_width, len(c.knobs),
                                                   c.obs_history, self.actor_features, c.start_head)
        self._history = FeatureHistory(len(c.knobs), c.obs_history, self.actor_features)
        self.action_space = spaces.Box(-1.0, 1.0, (self.mapper.action_dim,), np.float32)

        self._sim: Simulation | None = None
        self._loop: ClosedLoop | None = None
        self.weather = self.start_weather
        self.records: list[StepRecord] = []
        self.scene_index = -1
        self.episode_seed = -1
        #: the seed of the world's own randomness this episode (traffic behaviour, sensor noise, the system's
        #: own draws): the episode seed unless ``reset`` was given ``world_seed``, which a benchmark does to
        #: re-run a failure in a world its adversary never saw
        self.world_seed = -1
        #: whether the next step chooses the start (env.start_head: the episode's first action)
        self.choosing_start = False
        #: env.start_bonus: the starts this env chose, per cell of the held knobs' actions, and the bonus the
        #: episode's first tick pays
        self.start_counts: dict[tuple[int, ...], int] = {}
        self._pending_bonus = 0.0
        if c.start_head and not self.held_knobs:
            raise UserInputError(f"env.start_head = true, but no knob among env.knobs {list(c.knobs)} is held over "
                                 f"an episode of {c.episode_steps} steps under dynamics '{c.dynamics}': there is "
                                 "no start to choose (leave start_head out)")
        not_held = [k for k in c.start_bonus_knobs if k not in self.held_knobs]
        if c.start_bonus and not_held:
            raise UserInputError(f"env.start_bonus_knobs: {not_held} are not held over an episode (the start head "
                                 f"chooses only the held knobs); allowed: {', '.join(self.held_knobs)}")

    # -- observation -------------------------------------------------------------------------------------
    def _observation(self, push: bool = True) -> Any:
        """The observation after the loop's latest perception (a reset or a step): it pushes that step's
        features onto the history, so call it once per reset and per step (``push`` False: the observation
        the history already holds, as ``restore`` returns it)."""
        assert self._loop is not None and self._loop.frame is not None
        c, mode = self.config, self.config.observation_mode
        out: dict[str, Any] = {}
        if mode != "features":
            rgb = self._loop.frame.rgb
            if rgb.shape[:2] != (c.obs_height, c.obs_width):
                rgb = cv2.resize(rgb, (c.obs_width, c.obs_height), interpolation=cv2.INTER_AREA)
            out["image"] = rgb
        if mode == "image+knobs":
            out["knobs"] = self.weather.normalized(c.knobs)
        if mode in ("features", "image+features"):
            loop = self._loop
            neighbour = loop.sim.neighbour_ahead() if NEIGHBOUR_FEATURES[0] in self.actor_features else None
            row = step_features(self.weather, tuple(c.knobs), loop.ego.speed, loop.sim.step_count * loop.sim.dt,
                                loop.output, loop.sim.lead() if self.actor_features else None, self.actor_features,
                                neighbour)
            out["features"] = self._history.push(row) if push else self._history.vector()
            if c.start_head:  # the start step's flag, once after the stacked rows
                out["features"] = np.append(out["features"], np.float32(self.choosing_start))
        if mode == "image":
            return out["image"]
        if mode == "features":
            return out["features"]
        return out

    # -- gymnasium API -----------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """Sample a scene (or take ``options['scene']``) and an episode seed from the env's generator. With
        ``env.start_head`` the first step chooses the start (``options['start_head']`` False: not this episode,
        which then starts at ``options['weather']`` or the env's start as usual)."""
        super().reset(seed=seed)

        self._close_sim()
        options = options or {}
        n = len(self.catalog.scenes)
        idx = int(options["scene"]) if "scene" in options else int(self.np_random.integers(n))
        if not 0 <= idx < n:
            raise UserInputError(f"reset option scene = {idx} is out of range; the catalog has {n} scenes")
        self.scene_index = idx
        self.episode_seed = int(options.get("episode_seed", self.np_random.integers(2**31 - 1)))
        self.world_seed = int(options.get("world_seed", self.episode_seed))
        self.choosing_start = bool(options.get("start_head", self.config.start_head))
        self._pending_bonus = 0.0
        if self.choosing_start and not self.config.start_head:
            raise UserInputError("reset option start_head = true needs env.start_head = true (the observation "
                                 "carries the start step's flag only then)")
        self._begin(options.get("weather", self.exploring_start(self.episode_seed)))
        info = {"scene": idx, "episode_seed": self.episode_seed, "world_seed": self.world_seed,
                "knobs": self._knob_info()}
        return self._observation(), info

    def _begin(self, weather: Weather) -> None:
        """The episode's simulation from ``weather``: the scene as the seed builds it and the first frame."""
        self._close_sim()
        self.weather = weather
        #: the weather this episode started from (records keep it, so a replay starts there too)
        self.episode_start = weather
        scene = self.catalog.scene(self.scene_index)
        self._sim = self.backend.create_simulation(scene, seed=self.world_seed, weather=weather, camera=self.camera)
        self._loop = ClosedLoop(self._sim, self.system, self.backend.name, self.world_seed)
        self._loop.start(weather)
        self._history.reset()
        self.reward_fn.reset()
        self.records = []

    # -- snapshots -----------------------------------------------------------------------------------------
    def snapshot(self) -> EnvSnapshot:
        """The episode as it stands (``env/snapshot.py``): ``restore`` returns to it exactly, so that the same
        actions from there give the same step records, to the bit, as the uninterrupted run. Backends that
        cannot save a world (CARLA) refuse with a message that says so."""
        loop, sim = self._loop, self._sim
        if loop is None or sim is None or loop.frame is None or loop.output is None:
            raise RuntimeError("call reset() before snapshot()")
        world = sim.snapshot()  # first: a backend without snapshots refuses before anything is copied
        return EnvSnapshot(self.scene_index, self.episode_seed, self.world_seed, sim.step_count, self.weather,
                           self.episode_start, tuple(self.records), world, copy_state(self.system),
                           copy.deepcopy(loop.frame), loop.ego, copy.deepcopy(loop.output),
                           copy.deepcopy(self._history), copy_state(self.reward_fn, shared=(self.rulebook,)),
                           self.choosing_start, self._pending_bonus)

    def restore(self, snapshot: EnvSnapshot) -> Any:
        """Return to ``snapshot`` (taken by this env or one with the same config) and give its observation; the
        env's own generator (which picks the next ``reset``'s scene) is not rewound."""
        if not isinstance(snapshot, EnvSnapshot):
            raise TypeError(f"restore takes an EnvSnapshot, not {type(snapshot).__name__}")
        scene = self.catalog.scene(snapshot.scene_index)
        if self._sim is None or self.scene_index != snapshot.scene_index:
            self._close_sim()
            self._sim = self.backend.create_simulation(scene, seed=snapshot.world_seed, weather=snapshot.weather,
                                                       camera=self.camera)
        self._sim.restore(snapshot.world)
        self.system = copy_state(snapshot.system)
        self._loop = loop = ClosedLoop(self._sim, self.system, self.backend.name, snapshot.world_seed,
                                       reset_system=False)
        loop.frame, loop.ego, loop.output = copy.deepcopy(snapshot.frame), snapshot.ego, copy.deepcopy(snapshot.output)
        self._sim.apply_ego_control(loop.output.control)
        self.scene_index, self.episode_seed, self.world_seed = (snapshot.scene_index, snapshot.episode_seed,
                                                                snapshot.world_seed)
        self.weather, self.episode_start = snapshot.weather, snapshot.episode_start
        self.records = list(snapshot.records)
        self._history = copy.deepcopy(snapshot.history)
        self.reward_fn = copy_state(snapshot.reward, shared=(self.rulebook,))
        self.choosing_start, self._pending_bonus = snapshot.choosing_start, snapshot.pending_bonus
        return self._observation(push=False)

    def chosen_start(self, action: np.ndarray) -> Weather:
        """The start a start-head action names. Each held knob's action keeps the episode's start at 0 and
        reaches the knob's low end at -1 and its high end at +1 (so an untrained head starts where every
        episode would), except the sun's azimuth: its action is the sun's bearing from the ego's heading (0:
        straight ahead, +-1: behind), so that one action means the same light on every scene, as a tester
        schedules a drive into the evening sun. The start is then kept inside the ODD at that heading (a glare
        start is refused where the ODD refuses glare); knobs that are not held keep the episode's start."""
        assert self._loop is not None
        heading = self._loop.heading_deg
        action = np.asarray(action, np.float64).reshape(-1)
        values = dict(self.episode_start.values)
        for name, i in zip(self.held_knobs, self.held_indices(), strict=True):
            a, spec, now = float(np.clip(action[i], -1.0, 1.0)), KNOBS[name], values[name]
            if name == "sun_azimuth_angle":
                values[name] = spec.fit(heading + 180.0 * a)
            elif self.config.start_action == "absolute":
                values[name] = spec.low + (a + 1.0) / 2.0 * spec.span
            else:
                values[name] = now + a * ((now - spec.low) if a < 0 else (spec.high - now))
        proposed = Weather(values)
        if self.odd is not None and self.config.odd_keep_inside:
            return self.odd.keep_inside(self.episode_start, proposed, self.conditions_model, heading)
        return proposed

    @property
    def heading_deg(self) -> float:
        """The ego camera's heading now [deg, counter-clockwise from east]: glare and the sun's bearing are
        taken from it."""
        if self._loop is None:
            raise RuntimeError("call reset() before heading_deg")
        return float(self._loop.heading_deg)

    @property
    def held_knobs(self) -> tuple[str, ...]:
        """The knobs the agent turns that an episode can barely move (all its steps reach under
        ``HELD_REACH`` of the range: under natural dynamics the sun, 0.25 deg a minute, whose position is the
        time of day). Only the start sets them, so an adversary that is to reach a low sun must choose the
        start (``start_from``, ``natural_start``)."""
        steps = self.config.episode_steps
        return tuple(k for k, d in zip(self.mapper.knobs, self.mapper.max_delta, strict=True)
                     if d * steps < HELD_REACH * KNOBS[k].span and k not in self.config.disabled_knobs
                     and not KNOBS[k].is_actor)

    def held_indices(self) -> list[int]:
        """Where the held knobs sit in the action vector (``held_knobs`` order)."""
        knobs = list(self.mapper.knobs)
        return [knobs.index(k) for k in self.held_knobs]

    def start_from(self, position: Sequence[float]) -> Weather:
        """The start weather with each held knob at ``position`` (0..1 of its range, in ``held_knobs`` order),
        moved back inside the ODD as far as needed (a position outside lands on the ODD's boundary)."""
        held = self.held_knobs
        if len(position) != len(held):
            raise UserInputError(f"a start position has {len(position)} value(s); the held knobs are {list(held)}")
        values = dict(self.start_weather.values)
        for name, u in zip(held, position, strict=True):
            spec = KNOBS[name]
            values[name] = spec.low + float(np.clip(u, 0.0, 1.0)) * spec.span
        proposed = Weather(values)
        if self.odd is not None and self.config.odd_keep_inside:
            return self.odd.keep_inside(self.start_weather, proposed, self.conditions_model)
        return proposed

    def natural_start(self, rng: np.random.Generator, tries: int = 200) -> Weather:
        """A start drawn uniformly over the held knobs' ranges inside the ODD (rejection sampling; the start
        weather when ``tries`` draws all fall outside): the placeholder nominal start distribution (a time of
        day and a heading, uniform) until a climatological one replaces it."""
        held = self.held_knobs
        for _ in range(tries):
            values = dict(self.start_weather.values)
            for name in held:
                spec = KNOBS[name]
                values[name] = float(rng.uniform(spec.low, spec.high))
            drawn = Weather(values)
            if self.odd is None or not self.config.odd_keep_inside or self.odd.contains(
                    self.conditions_model.conditions(drawn, None), drawn):
                return drawn
        return self.start_weather

    def exploring_start(self, episode_seed: int) -> Weather:
        """The episode's start weather: ``start_weather``, or with ``env.start_spread`` > 0 each knob the agent
        turns drawn uniformly within ``start_spread`` of its reach in an episode (its largest change per step
        times the steps) around it, then kept inside the ODD. Why: under natural dynamics a policy that
        starts every episode in clear air never sees dense fog within the paper's budget, so it cannot learn
        what fog is worth (docs/results/07-reactive-adversary-in-odd.md). Drawn from the episode seed, so a checkpoint's
        episode is rebuilt exactly."""
        c = self.config
        if c.start_spread <= 0:
            return self.start_weather
        rng = np.random.default_rng([int(episode_seed), 0x57A27])
        moved = dict(self.start_weather.values)
        for name, delta in zip(self.mapper.knobs, self.mapper.max_delta, strict=True):
            spec = KNOBS[name]
            if name in c.disabled_knobs or spec.is_actor:  # traffic starts as the scene has it
                continue
            reach = min(spec.span, float(delta) * c.episode_steps) * c.start_spread
            base = moved[name]
            lo, hi = (base - reach, base + reach) if spec.wraps else \
                (max(spec.low, base - reach), min(spec.high, base + reach))
            value = float(rng.uniform(lo, hi))
            moved[name] = spec.fit(value)  # a range inside the knob's already, unless it wraps
        drawn = Weather(moved)
        if self.odd is not None and c.odd_keep_inside:
            drawn = self.odd.keep_inside(self.start_weather, drawn, self.conditions_model)
        return drawn

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        if self._loop is None:
            raise RuntimeError("call reset() before step()")
        if self.choosing_start:  # the start step: no tick, no reward; the episode begins from the chosen start
            self.choosing_start = False
            self._begin(self.chosen_start(action))
            if self.config.start_bonus:
                self._pending_bonus = self.start_bonus(action)
            start = {k: float(self.weather[k]) for k in self.held_knobs}
            if "sun_azimuth_angle" in start:  # the sun's bearing from the heading: what the head chose
                start["sun_bearing"] = (start["sun_azimuth_angle"] - self._loop.heading_deg + 180.0) % 360.0 - 180.0
            return self._observation(), 0.0, False, False, {"start_step": True, "knobs": self._knob_info(),
                                                           "start": start}
        before = self.weather
        proposed = self.mapper.apply(before, action)
        if self.odd is not None and self.config.odd_keep_inside:
            proposed = self.odd.keep_inside(before, proposed, self.conditions_model, self._loop.heading_deg)
        obs, reward, terminated, truncated, info = self.step_weather(proposed, before)
        if self._pending_bonus:  # the start head's count bonus, paid once at the episode's first tick
            reward, info["start_bonus"], self._pending_bonus = reward + self._pending_bonus, self._pending_bonus, 0.0
        return obs, reward, terminated, truncated, info

    def start_bonus(self, action: np.ndarray) -> float:
        """Count the start ``action`` chose in its cell (``start_bonus_cells`` per counted held knob's action) and
        return ``start_bonus / sqrt(n)``, n the starts this env has chosen in that cell (this one included)."""
        c = self.config
        counted = [i for k, i in zip(self.held_knobs, self.held_indices(), strict=True)
                   if not c.start_bonus_knobs or k in c.start_bonus_knobs]
        a = np.clip(np.asarray(action, np.float64).reshape(-1)[counted], -1.0, 1.0)
        cell = tuple(int(min(c.start_bonus_cells - 1, (x + 1.0) / 2.0 * c.start_bonus_cells)) for x in a)
        self.start_counts[cell] = n = self.start_counts.get(cell, 0) + 1
        return float(c.start_bonus) / math.sqrt(n)

    def step_weather(self, weather: Weather, before: Weather | None = None
                     ) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """One step under ``weather`` as given (``step`` after mapping and the ODD; a counterfactual replay
        plays a recorded trajectory through it): tick, conditions, rules, reward."""
        if self._loop is None:
            raise RuntimeError("call reset() before step_weather()")
        before = before or self.weather
        self.weather = weather
        rec = self._loop.advance(weather)
        if self.odd is not None and rec.conditions is not None:
            rec = replace(rec, odd_status=self.odd.status(rec.conditions, weather))
        rule_terms = self.rulebook.step_terms(rec)
        surprise = self.weather_model.surprise(before.values, weather.values, self.dt) \
            if self.config.reward.naturalness_weight > 0 else 0.0
        rec = rec.scored(rule_terms, self.reward_fn.step_terms(rec, rule_terms, surprise))
        self.records.append(rec)
        terminated = bool(self.config.terminate_on_collision and rec.collision.collided) or \
            self.reward_fn.is_failure(rec)
        truncated = len(self.records) >= self.config.episode_steps
        info = step_info(rec, self._knob_info())
        if terminated or truncated:
            info["episode_violations"] = self.rulebook.violations(self.records)
        return self._observation(), float(rec.reward["reward"]), terminated, truncated, info

    def camera_frame(self) -> np.ndarray:
        """The system's current camera image (RGB, full resolution), e.g. to keep frames of a failure."""
        if self._loop is None or self._loop.frame is None:
            raise RuntimeError("call reset() before camera_frame()")
        return self._loop.frame.rgb

    def _knob_info(self) -> dict[str, float]:
        return {k: float(self.weather[k]) for k in self.config.knobs}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self._loop is None or self._loop.frame is None:
            return None

        if self.records:
            return annotate_frame(self._loop.frame.rgb, self.records[-1])
        return self._loop.frame.rgb.copy()

    def actor_events(self) -> list[ActorEvent]:
        """What the actor knobs made happen in the current episode (``Simulation.actor_events``)."""
        return [] if self._sim is None else self._sim.actor_events()

    def _close_sim(self) -> None:
        if self._sim is not None:
            self._sim.destroy()
        self._sim = None
        self._loop = None

    def close(self) -> None:
        self._close_sim()
        self.backend.close()
