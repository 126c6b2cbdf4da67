"""One campaign episode: a policy plays a scene in the env, and the episode's files are written.

``CampaignRunner`` is one worker's environment (it implements ``policies.EpisodeRunner``): it plays a
policy's actions on a scene and keeps camera frames around the first collision. ``write_episode`` writes
the step Parquet, the frames, the edge-case record and, last, the summary row that marks the episode done.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from genesis_rl.config import from_mapping
from genesis_rl.drive import write_telemetry
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
from genesis_rl.evaluation.campaign_files import episode_name, episode_path, steps_path
from genesis_rl.evaluation.campaign_spec import CampaignSpec
from genesis_rl.evaluation.failure_modes import LABELLER_VERSION, label_collision
from genesis_rl.evaluation.policies import EpisodeOutcome
from genesis_rl.evaluation.records import make_record, save_record
from genesis_rl.io_utils import atomic_write, atomic_write_json
from genesis_rl.rules.rulebook import Rulebook


class CampaignRunner:
    """One worker's environment: plays a policy's actions on a scene and captures frames around the
    first collision. Implements ``policies.EpisodeRunner``."""

    def __init__(self, spec: CampaignSpec, folder: Path) -> None:
        env_cfg = {**spec.env, "catalog": str(folder / "catalog.json"), "episode_steps": spec.steps}
        self.config = from_mapping(EnvConfig, env_cfg, "env")
        self.env = GenesisEnv(self.config)
        self.spec = spec

    def run(self, act: Callable[[Any], np.ndarray], scene: int, episode_seed: int) -> EpisodeOutcome:
        env, spec = self.env, self.spec
        obs, _ = env.reset(options={"scene": scene, "episode_seed": episode_seed})
        ring: deque[tuple[int, np.ndarray]] = deque(maxlen=spec.frames_before + 1)
        frames: dict[int, np.ndarray] = {}
        hit_step: int | None = None
        for _ in range(spec.steps):
            obs, _, terminated, truncated, _ = env.step(act(obs))
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
        return EpisodeOutcome(list(env.records), frames, sim_steps=len(env.records))

    def close(self) -> None:
        self.env.close()


def write_episode(folder: Path, spec: CampaignSpec, runner: CampaignRunner, policy: str, scene: int,
                  episode_seed: int, outcome: EpisodeOutcome, seconds: float) -> dict[str, Any]:
    env = runner.env
    name = episode_name(scene)
    records = outcome.records
    write_telemetry(steps_path(folder, policy, scene), records)
    row = episode_row(policy, scene, episode_seed, outcome, env.rulebook, env.config.knobs)
    row["seconds"] = round(seconds, 2)
    for step, rgb in sorted(outcome.frames.items()):
        _write_jpeg(folder / "frames" / policy / name / f"step_{step:04d}.jpg", rgb)
    failed = row["collision_events"] > 0 or any(row["violations"][r.name] > 0 for r in env.rulebook.rules if r.in_total)
    if spec.records == "all" or failed:
        record = make_record(spec, runner, policy, scene, episode_seed, records, row)
        save_record(folder / "records" / f"{policy}_{name}.json", record)
        row["record"] = f"records/{policy}_{name}.json"
    atomic_write_json(episode_path(folder, policy, scene), row, indent=1)  # last: marks it done
    return row


def _write_jpeg(path: Path, rgb: np.ndarray) -> None:
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
