"""One campaign episode: a policy plays a scene in the env, and the episode's files are written.

``CampaignRunner`` is one worker's environment (it implements ``adversaries.EpisodeRunner``): it plays a
policy's actions on a scene and keeps camera frames around the first collision. ``write_episode`` writes
the step Parquet, the frames, the edge-case record and, last, the summary row that marks the episode done.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from genesis_rl.adversaries import EpisodeOutcome
from genesis_rl.campaigns.campaign_files import episode_path, steps_path
from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.campaigns.records import make_record, save_record
from genesis_rl.core.config import from_mapping
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.labels.blame import blame_label, reference_name, visibility_evidence
from genesis_rl.labels.careful_driver import careful_driver_evidence, event_for_collision
from genesis_rl.labels.distinct import rain_band, visibility_band, what_was_hit
from genesis_rl.labels.failure_modes import LABELLER_VERSION, label_collision
from genesis_rl.loop.drive import write_telemetry
from genesis_rl.loop.rules.rulebook import Rulebook
from genesis_rl.sim.interface import ActorEvent
from genesis_rl.world.knobs import Weather
from genesis_rl.world.odd.domain import STATUSES
from genesis_rl.world.step_record import StepRecord

#: after the recorded impact, how long the counterfactual replay drives on looking for a collision [s]
COUNTERFACTUAL_MARGIN_S = 2.0


class CampaignRunner:
    """One worker's environment: plays a policy's actions on a scene and captures frames around the
    first collision. Implements ``adversaries.EpisodeRunner``."""

    def __init__(self, spec: CampaignSpec, folder: Path, env_settings: dict[str, Any] | None = None) -> None:
        # env_settings: this worker's own (e.g. its CARLA server, genesis_rl.distributed.servers)
        env_cfg = {**spec.env, **(env_settings or {}), "catalog": str(CampaignFolder(folder).catalog),
                   "episode_steps": spec.steps}
        self.config = from_mapping(EnvConfig, env_cfg, "env")
        self.env = GenesisEnv(self.config)
        self.spec = spec
        self._oracle: GenesisEnv | None = None

    @property
    def held_knobs(self) -> tuple[str, ...]:
        """The knobs only the start can set (``GenesisEnv.held_knobs``), in the action vector's order."""
        return self.env.held_knobs

    def held_indices(self) -> list[int]:
        return self.env.held_indices()

    def start_from(self, position: Sequence[float]) -> Weather:
        return self.env.start_from(position)

    def natural_start(self, rng: np.random.Generator) -> Weather:
        return self.env.natural_start(rng)

    @property
    def knobs(self) -> tuple[str, ...]:
        return tuple(self.config.knobs)

    @property
    def has_start_head(self) -> bool:
        return self.config.start_head

    #: the world seed of every episode this runner plays (None: each episode's own seed); set by
    #: ``in_world`` for the benchmark's re-runs, never seen by a policy
    world_seed: int | None = None

    def in_world(self, world_seed: int | None) -> CampaignRunner:
        """This runner with the world's randomness drawn from ``world_seed`` from now on (None: as before)."""
        self.world_seed = None if world_seed is None else int(world_seed)
        return self

    @property
    def last_record(self) -> StepRecord | None:
        """The latest step's record (None before the first step): what a tester watching the drive sees, the
        system's detections and the ego's state included; a reactive scripted policy acts on it."""
        return self.env.records[-1] if self.env.records else None

    def run(self, act: Callable[[Any], np.ndarray], scene: int, episode_seed: int,
            start: Weather | None = None, start_head: bool = False) -> EpisodeOutcome:
        """One episode; ``start``: the weather it starts from (None: the env's start weather); ``start_head``:
        ``act``'s first action chooses it instead (``GenesisEnv.chosen_start``; the env needs start_head)."""
        env = self.env
        obs, _ = env.reset(options=self._reset_options(scene, episode_seed, start, start_head))
        if start_head:  # the start step: the env begins the episode where the action says
            obs, *_ = env.step(act(obs))
        state = {"obs": obs}

        def step(i: int) -> tuple[bool, bool]:
            state["obs"], _, terminated, truncated, _ = env.step(act(state["obs"]))
            return terminated, truncated

        return self._play(step)

    def play_schedule(self, scene: int, episode_seed: int, start: Weather | None,
                      schedule: Sequence[Weather]) -> EpisodeOutcome:
        """One episode whose weather follows ``schedule`` open loop from ``start`` (no policy acts; after its
        last entry the weather holds): a schedule tuned on other scenes, played on this one, with the frames
        and fields of any episode (``replay`` returns only the records)."""
        if not schedule:
            raise UserInputError("a schedule to play holds no step")
        env = self.env
        env.reset(options=self._reset_options(scene, episode_seed, start))

        def step(i: int) -> tuple[bool, bool]:
            _, _, terminated, truncated, _ = env.step_weather(schedule[min(i, len(schedule) - 1)])
            return terminated, truncated

        return self._play(step)

    def _play(self, step: Callable[[int], tuple[bool, bool]]) -> EpisodeOutcome:
        """The episode after its reset: ``step(i)`` plays step ``i`` (returns terminated, truncated), the frames
        around the first collision are kept."""
        env, spec = self.env, self.spec
        ring: deque[tuple[int, np.ndarray]] = deque(maxlen=spec.frames_before + 1)
        frames: dict[int, np.ndarray] = {}
        hit_step: int | None = None
        for i in range(spec.steps):
            terminated, truncated = step(i)
            rec = env.records[-1]
            rgb = env.camera_frame()
            if hit_step is None:
                ring.append((rec.step, rgb))
                if rec.collision.collided:
                    hit_step = rec.step
                    frames.update((s, f) for s, f in ring if (hit_step - s) % spec.frame_stride == 0)
            elif rec.step <= hit_step + spec.frames_after and (rec.step - hit_step) % spec.frame_stride == 0:
                frames[rec.step] = rgb
            if terminated or truncated:
                break
        trajectory = [env.episode_start.values, *(r.knobs for r in env.records)]
        return EpisodeOutcome(list(env.records), frames, sim_steps=len(env.records), actor_events=env.actor_events(),
                              start=env.episode_start,
                              naturalness=env.weather_model.naturalness(trajectory, env.dt))

    # -- adversaries.ExploringRunner: an explorer steps the episode itself and returns to saved states ------
    def begin(self, scene: int, episode_seed: int, start: Weather | None = None) -> None:
        self.env.reset(options=self._reset_options(scene, episode_seed, start))

    def step(self, action: np.ndarray) -> StepRecord:
        self.env.step(action)
        return self.env.records[-1]

    @property
    def steps_taken(self) -> int:
        return len(self.env.records)

    @property
    def heading_deg(self) -> float:
        return self.env.heading_deg

    def snapshot(self) -> object:
        return self.env.snapshot()

    def restore(self, snapshot: object) -> None:
        self.env.restore(snapshot)  # type: ignore[arg-type]

    def _reset_options(self, scene: int, episode_seed: int, start: Weather | None,
                       start_head: bool = False) -> dict[str, Any]:
        """``GenesisEnv.reset``'s options for an episode of this runner (its world seed, when set)."""
        options: dict[str, Any] = {"scene": scene, "episode_seed": episode_seed, "start_head": start_head}
        if self.world_seed is not None:
            options["world_seed"] = self.world_seed
        if start is not None:
            options["weather"] = start
        return options

    def replay(self, scene: int, episode_seed: int, start: Weather | None,
               schedule: Sequence[Weather]) -> list[StepRecord]:
        """A recorded weather trajectory played open loop from ``start`` (no policy acts): how a benchmark judges
        a schedule in another world (``in_world``)."""
        self.env.reset(options=self._reset_options(scene, episode_seed, start))
        for weather in schedule:
            self.env.step_weather(weather)
        return list(self.env.records)

    def oracle_collides(self, scene: int, episode_seed: int, records: Sequence[StepRecord], hit_at: int,
                        start: Weather | None = None) -> bool:
        """The counterfactual: the same scene, seeds, start and weather trajectory, driven by the ``oracle``
        system (the same controller on ground-truth boxes). Does it collide by the recorded impact (plus a
        margin)?"""
        if self._oracle is None:
            self._oracle = GenesisEnv(replace(self.config, system="oracle", system_kwargs={}))
        env = self._oracle
        env.reset(options=self._reset_options(scene, episode_seed, start))
        end = min(len(records), hit_at + 1 + int(round(COUNTERFACTUAL_MARGIN_S / env.dt)))
        for rec in records[:end]:
            env.step_weather(Weather.from_recorded(rec.knobs))
            if env.records[-1].collision.collided:
                return True
        return False

    def close(self) -> None:
        self.env.close()
        if self._oracle is not None:
            self._oracle.close()


def write_episode(folder: Path, spec: CampaignSpec, runner: CampaignRunner, policy: str, scene: int,
                  episode_seed: int, outcome: EpisodeOutcome, seconds: float,
                  lost: Sequence[str] = ()) -> dict[str, Any]:
    """Write one episode's files (its row last). ``lost``: why earlier attempts lost the simulator (the row's
    ``simulator_lost``, present only when the episode was retried)."""
    env = runner.env
    records = outcome.records
    write_telemetry(steps_path(folder, policy, scene), records)
    row = episode_row(policy, scene, episode_seed, outcome, env.rulebook, env.config.knobs)
    if outcome.actor_events:
        row["actor_events"] = [e.as_dict() for e in outcome.actor_events]
    add_natural_fields(row, runner, scene, episode_seed, records, outcome.actor_events, outcome.start)
    row["seconds"] = round(seconds, 2)
    if lost:
        row["simulator_lost"] = list(lost)
    paths = CampaignFolder(folder)
    for step, rgb in sorted(outcome.frames.items()):
        write_jpeg(paths.frames(policy, scene) / f"step_{step:04d}.jpg", rgb)
    failed = row["collision_events"] > 0 or any(row["violations"][r.name] > 0 for r in env.rulebook.rules if r.in_total)
    if spec.records == "all" or failed:
        record = make_record(spec, runner, policy, scene, episode_seed, records, row, outcome.start)
        save_record(paths.record(policy, scene), record)
        row["record"] = paths.record(policy, scene).relative_to(paths.root).as_posix()
    atomic_write_json(episode_path(folder, policy, scene), row, indent=1)  # last: marks it done
    return row


def add_natural_fields(row: dict[str, Any], runner: CampaignRunner, scene: int, episode_seed: int,
                       records: Sequence[StepRecord], actor_events: Sequence[ActorEvent] = (),
                       start: Weather | None = None) -> None:
    """What makes a failure a natural edge case, added to the episode's row: its steps' ODD labels, the
    weather trajectory's log-likelihood, and for a collision the conditions and ODD status at the impact,
    the visibility evidence, the counterfactual oracle replay (when ``counterfactual`` is on: by default with
    an ODD), the careful-driver reference when an actor knob acted on the vehicle hit (``careful_driver``),
    the blame and the reference that decided it, what was hit and the failure's cluster fields
    (``evaluation.distinct``)."""
    env = runner.env
    if not records:
        return
    trajectory = [(start or env.start_weather).values, *(r.knobs for r in records)]
    model = env.weather_model
    row["naturalness"] = {"log_likelihood": round(model.log_likelihood(trajectory, env.dt), 3),
                          "ratio_to_held": round(model.naturalness(trajectory, env.dt), 3)}
    if env.odd is not None:
        row["odd"] = {s: sum(1 for r in records if r.odd_status == s) for s in STATUSES}
    failure = row.get("failure")
    if not failure:
        return
    hit_at = next(i for i, r in enumerate(records) if r.collision.collided)
    at = records[hit_at]
    evidence = visibility_evidence(records, hit_at, env.dt)
    run_oracle = bool(runner.spec.options.get("counterfactual", env.odd is not None))
    oracle = runner.oracle_collides(scene, episode_seed, records, hit_at, start) if run_oracle else None
    event = event_for_collision(actor_events, records, hit_at)
    careful = None if event is None else careful_driver_evidence(records, hit_at, event, env.dt)
    c = at.conditions
    failure.update(
        naturalness=round(model.naturalness(trajectory[:hit_at + 2], env.dt), 3),
        odd_status=at.odd_status or "no ODD",
        conditions=None if c is None else c.as_dict(),
        visibility=None if c is None else visibility_band(c.visibility_m),
        rain=None if c is None else rain_band(c.rain_mm_h),
        light=None if c is None else c.light,
        road_state=None if c is None else c.road_state,
        hit=what_was_hit(records, hit_at, env.dt, list(actor_events)),
        evidence=evidence,
        oracle_collides=oracle,
        blame=blame_label(evidence, oracle, careful),
        reference=reference_name(careful),
    )
    if careful is not None:
        failure["careful_driver"] = careful


def write_jpeg(path: Path, rgb: np.ndarray) -> None:
    atomic_write(path, lambda p: Image.fromarray(rgb).save(p, format="JPEG", quality=92))


def episode_row(policy: str, scene: int, episode_seed: int, outcome: EpisodeOutcome, rulebook: Rulebook,
                knobs: Sequence[str]) -> dict[str, Any]:
    """One episode's summary: every rule's violation (a column each, by priority, then ``total``), collisions and their
    failure mode, IoU, return, knobs."""
    recs = outcome.records
    violations = rulebook.violations(recs)
    hits = np.array([r.collision.collided for r in recs], bool)
    events = int(hits[0]) + int((hits[1:] & ~hits[:-1]).sum()) if len(hits) else 0
    failure = label_collision(recs)
    gap = np.array([r.lead.true_distance for r in recs], float)
    scores = {**violations, "total": rulebook.total(violations)}
    row: dict[str, Any] = {
        "policy": policy, "scene": scene, "episode_seed": episode_seed, "steps": len(recs),
        **{k: round(v, 6) for k, v in scores.items()},
        "violations": {k: round(v, 6) for k, v in violations.items()},
        "collision_events": events,
        "first_collision_step": failure["step"] if failure else None,
        "collision_speed": round(failure["speed"], 3) if failure else 0.0,
        "failure_mode": failure["mode"] if failure else None,
        "failure": failure,
        "labeller_version": LABELLER_VERSION,
        "min_gap": round(float(np.nanmin(gap)), 3) if np.isfinite(gap).any() else None,
        "mean_iou": round(float(np.mean([r.iou for r in recs])), 4) if recs else None,
        "return": round(outcome.total_reward, 4),
        "sim_steps": outcome.sim_steps,
        "knobs_mean": {k: round(float(np.mean([r.knobs[k] for r in recs])), 3) for k in knobs} if recs else {},
        "knobs_final": {k: round(float(recs[-1].knobs[k]), 3) for k in knobs} if recs else {},
        "extra": outcome.extra,
    }
    return row


# -- the campaign ---------------------------------------------------------------------------------------
