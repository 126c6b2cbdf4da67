"""One drawn episode, played: the scene, the start and the step actions come from the driver (so the
results are the same whatever the number of workers); the worker says whether it failed inside the ODD."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from genesis_rl.adversaries.base import in_odd_failure_at
from genesis_rl.core.config import from_mapping
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.estimation.nominal import BEARING, BRAKE_DECEL, BRAKE_ONSET, EVENTS
from genesis_rl.labels.distinct import rain_band, visibility_band, what_was_hit
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.odd.domain import IN_ODD
from genesis_rl.world.step_record import StepRecord


@dataclass(frozen=True)
class EpisodeTask:
    """What the driver drew for episode ``index``: its scene, seeds and start (nominal variables)."""

    index: int
    scene: int
    episode_seed: int
    action_seed: tuple[int, ...]
    start: dict[str, float]


def start_weather(env: GenesisEnv, start: dict[str, float], heading_deg: float) -> Weather:
    """The start weather: the env's start with each drawn held knob set (the bearing turned into the sun's
    azimuth at the ego's heading)."""
    values = dict(env.start_weather.values)
    for name, v in start.items():
        if name in EVENTS:  # played by braking_action, step by step
            continue
        if name == BEARING:
            values["sun_azimuth_angle"] = KNOBS["sun_azimuth_angle"].fit(heading_deg + v)
        else:
            values[name] = v
    return Weather(values)


def braking_action(env: GenesisEnv, start: dict[str, float], step: int, i: int) -> float:
    """The ``lead_decel`` action (the mapper's knob ``i``) of ``step`` that plays the drawn braking event: hold 0
    until the onset, then move toward the event's deceleration as fast as the knob's natural rate allows (a
    deterministic function of the event and the knob's value, so the likelihood ratio of an episode is its
    start's alone)."""
    now = float(env.weather["lead_decel"])
    target = start[BRAKE_DECEL] if (step + 1) * env.dt >= start[BRAKE_ONSET] else 0.0
    limit = float(env.mapper.max_delta[i])
    return float(np.clip((target - now) / limit, -1.0, 1.0)) if limit > 0 else 0.0


#: the danger score's cap [1/s]: a contact (gap 0) or a gap closing ten times a second counts as the same
DANGER_CAP = 10.0


def danger(records: Sequence[StepRecord]) -> float:
    """How near the episode came to hitting its lead: the largest inverse time-to-collision over its steps,
    closing speed over gap [1/s] (0 when the gap never closed; a contact counts as the cap). Cross-entropy
    ranks episodes that did not fail by it: a near miss scores high whatever the rest of the episode did, where
    the summed reward mostly measures the scene (docs/estimation.md)."""
    worst = 0.0
    for r in records:
        if r.collision.collided:
            return DANGER_CAP
        lead = r.lead
        if lead.present and math.isfinite(lead.true_distance) and math.isfinite(lead.speed):
            closing = r.ego.speed - lead.speed
            if closing > 0:
                worst = max(worst, min(DANGER_CAP, closing / max(lead.true_distance, 0.1)))
    return worst


def play(env: GenesisEnv, task: EpisodeTask, steps: int) -> dict[str, Any]:
    """Play ``task`` for ``steps`` steps with the nominal step actions; the row that describes it."""
    env.reset(options={"scene": task.scene, "episode_seed": task.episode_seed})
    heading = env.heading_deg
    env.reset(options={"scene": task.scene, "episode_seed": task.episode_seed,
                       "weather": start_weather(env, task.start, heading)})
    actions = np.random.default_rng(list(task.action_seed)).uniform(
        -1.0, 1.0, (steps, env.mapper.action_dim)).astype(np.float32)
    score = 0.0
    event = BRAKE_DECEL in task.start
    brake_index = env.mapper.knobs.index("lead_decel") if event else -1
    for k, a in enumerate(actions):
        if event:
            a[brake_index] = braking_action(env, task.start, k, brake_index)
        _, reward, terminated, truncated, _ = env.step(a)
        score += float(reward)
        if terminated or truncated:
            break
    records = env.records
    hit = in_odd_failure_at(records)
    row: dict[str, Any] = {"index": task.index, "scene": task.scene, "episode_seed": task.episode_seed,
                           **{f"start_{k}": round(v, 6) for k, v in task.start.items()},
                           "heading": round(heading, 3), "steps": len(records), "score": round(score, 6),
                           "danger": round(danger(records), 6),
                           "in_odd_steps": sum(r.odd_status in IN_ODD for r in records),
                           "failed": hit is not None, "fail_step": hit, "cluster": None}
    if hit is not None:
        c = records[hit].conditions
        parts = [what_was_hit(records, hit, env.dt, env.actor_events())]
        if c is not None:
            parts += [c.light, "glare" if c.sun_glare else "no glare", visibility_band(c.visibility_m),
                      rain_band(c.rain_mm_h)]
        row["cluster"] = " / ".join(parts)
    return row


_WORKER: dict[str, Any] = {}


def init_worker(env_config: dict[str, Any], steps: int) -> None:
    """A worker process's env, built once (one torch thread: the same arithmetic in every process)."""
    torch.set_num_threads(1)
    _WORKER.update(env=GenesisEnv(from_mapping(EnvConfig, env_config, "env")), steps=steps)


def run_task(task: EpisodeTask) -> dict[str, Any]:
    return play(_WORKER["env"], task, _WORKER["steps"])
