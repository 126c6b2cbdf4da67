"""Evaluation campaigns: every policy drives the same held-out scenes with the same episode seeds.

The paper's testing protocol: scenes picked from the test catalog by the campaign seed, each with an
episode seed drawn from it, so NPC appearance and paths are identical across policies; 512 steps each.
Episodes run in worker processes. Each writes its own files and, last, its summary row, which marks it
done: an interrupted campaign resumes (``--resume``) without redoing finished episodes.

Layout of a campaign folder::

    campaign.json                    the spec, scenes, episode seeds, version, git commit
    catalog.json                     the test catalog the scenes come from
    episodes/<policy>/scene_NNNN.json     one summary row per episode (violations, failure mode, ...)
    steps/<policy>/scene_NNNN.parquet     every step: knobs, ego/lead state, controls, detections, IoU, rules
    frames/<policy>/scene_NNNN/step_NNNN.jpg  camera frames around the first collision
    records/<policy>_scene_NNNN.json      self-contained edge-case records (replayable)
    summary.json, episodes.csv            written by ``summarize_campaign``
"""

from __future__ import annotations

import json
import os
import shutil
import time
import warnings
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl import __version__, output_folder
from genesis_rl.errors import SimulatorLost, UserInputError
from genesis_rl.evaluation.failure_modes import (
    FAILURE_MODES,
    LABELLER_VERSION,
    FailureModeThresholds,
    label_collision,
)
from genesis_rl.evaluation.policies import POLICIES, EpisodeOutcome, PolicyContext, WeatherPolicy, resolve_policy
from genesis_rl.io_utils import atomic_write, atomic_write_json, atomic_write_text, read_json
from genesis_rl.knobs import KNOB_MODULES
from genesis_rl.plugins import import_modules, user_modules
from genesis_rl.rules.rulebook import RULES, Rulebook, default_rulebook, load_rulebook

CAMPAIGN_SCHEMA = "genesis-rl/campaign"
CAMPAIGN_VERSION = 1


@dataclass(frozen=True)
class CampaignSpec:
    """Everything that decides a campaign's results (``workers`` does not)."""

    policies: tuple[str, ...]
    map: str = "highway"
    catalog: str | None = None  # test catalog file; None: generate the map's default catalog
    catalog_seed: int = 0
    scenes: int = 50
    seed: int = 0
    steps: int = 512
    agent: str | None = None  # run folder or .zip of the trained agent
    env: dict[str, Any] = field(default_factory=dict)  # EnvConfig fields (from the agent's run)
    options: dict[str, Any] = field(default_factory=dict)  # policy options (search_budget, ...)
    records: str = "failures"  # edge-case records for: failures (collision or proximity violation), all
    frames_before: int = 40  # steps of camera frames kept before the first collision
    frames_after: int = 6
    frame_stride: int = 2

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["policies"] = list(self.policies)
        return d


def pick_scenes(n_catalog: int, count: int, seed: int) -> list[tuple[int, int]]:
    """(scene index, episode seed) pairs: ``count`` distinct scenes drawn by ``seed``, in catalog order."""
    if not 1 <= count <= n_catalog:
        raise UserInputError(f"--scenes = {count} must be in 1..{n_catalog} (the test catalog's size)")
    rng = np.random.default_rng(seed)
    indices = sorted(int(i) for i in rng.choice(n_catalog, size=count, replace=False))
    return [(i, int(np.random.default_rng([seed, i]).integers(0, 2**31 - 1))) for i in indices]


def episode_name(scene: int) -> str:
    return f"scene_{scene:04d}"


class CampaignRunner:
    """One worker's environment: plays a policy's actions on a scene and captures frames around the
    first collision. Implements ``policies.EpisodeRunner``."""

    def __init__(self, spec: CampaignSpec, folder: Path) -> None:
        from genesis_rl.config import from_mapping
        from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

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


# -- one episode, in a worker ---------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def plugin_modules() -> list[str]:
    """The user modules that registered a policy, a rule or a knob in this process (``@register_policy``,
    ``@register_rule``, ``register_knob``): spawned workers import them again, so the names resolve there."""
    return user_modules([*POLICIES.values(), *RULES.values()], KNOB_MODULES.values())


def _worker_init(spec_json: dict[str, Any], folder: str, torch_threads: int, plugins: Sequence[str] = ()) -> None:
    import torch  # local: start-up cost

    import_modules(plugins)
    torch.set_num_threads(torch_threads)
    spec_json = dict(spec_json)
    spec_json["policies"] = tuple(spec_json["policies"])
    _WORKER.clear()
    _WORKER.update(spec=CampaignSpec(**spec_json), folder=Path(folder), runner=None, policies={})


def _policy(name: str) -> WeatherPolicy:
    spec: CampaignSpec = _WORKER["spec"]
    if name not in _WORKER["policies"]:
        runner: CampaignRunner = _WORKER["runner"]
        ctx = PolicyContext(action_dim=runner.env.mapper.action_dim, seed=spec.seed,
                            agent_path=Path(spec.agent) if spec.agent else None,
                            options={**spec.options, "steps": spec.steps})
        _WORKER["policies"][name] = resolve_policy(name)(ctx)
    return _WORKER["policies"][name]


def run_task(task: tuple[str, int, int]) -> dict[str, Any]:
    """Play one (policy, scene, episode seed) and write its files; returns its summary row."""
    policy_name, scene, episode_seed = task
    spec: CampaignSpec = _WORKER["spec"]
    folder: Path = _WORKER["folder"]
    if _WORKER["runner"] is None:
        _WORKER["runner"] = CampaignRunner(spec, folder)
    runner: CampaignRunner = _WORKER["runner"]
    retries = int(spec.options.get("retries", 2))
    t0 = time.perf_counter()
    for attempt in range(retries + 1):
        try:
            outcome = _policy(policy_name).run_episode(runner, scene, episode_seed)
            break
        except SimulatorLost as err:  # nothing of this episode was written yet: reconnect and run it again
            if attempt == retries:
                raise
            warnings.warn(f"{policy_name} scene {scene}: simulator lost ({err}); reconnecting, retry "
                          f"{attempt + 1} of {retries}", stacklevel=1)
            try:
                runner.close()
            except Exception:  # noqa: BLE001 - the old connection is gone anyway
                pass
            runner = _WORKER["runner"] = CampaignRunner(spec, folder)
    seconds = time.perf_counter() - t0
    return write_episode(folder, spec, runner, policy_name, scene, episode_seed, outcome, seconds)


def write_episode(folder: Path, spec: CampaignSpec, runner: CampaignRunner, policy: str, scene: int,
                  episode_seed: int, outcome: EpisodeOutcome, seconds: float) -> dict[str, Any]:
    from genesis_rl.drive import write_telemetry
    from genesis_rl.evaluation.records import make_record, save_record

    env = runner.env
    name = episode_name(scene)
    records = outcome.records
    write_telemetry(folder / "steps" / policy / f"{name}.parquet", records)
    row = episode_row(policy, scene, episode_seed, outcome, env.rulebook, env.config.knobs)
    row["seconds"] = round(seconds, 2)
    for step, rgb in sorted(outcome.frames.items()):
        _write_jpeg(folder / "frames" / policy / name / f"step_{step:04d}.jpg", rgb)
    failed = row["collision_events"] > 0 or any(row["violations"][r.name] > 0 for r in env.rulebook.rules if r.in_total)
    if spec.records == "all" or failed:
        record = make_record(spec, runner, policy, scene, episode_seed, records, row)
        save_record(folder / "records" / f"{policy}_{name}.json", record)
        row["record"] = f"records/{policy}_{name}.json"
    atomic_write_json(folder / "episodes" / policy / f"{name}.json", row, indent=1)  # last: marks it done
    return row


def _write_jpeg(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

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
def run_folder_of(agent: Path) -> Path:
    """The training run folder of ``--agent``: a folder, its agent.zip, or a checkpoint inside it."""
    if agent.suffix != ".zip":
        return agent
    return agent.parent.parent if agent.parent.name == "checkpoints" else agent.parent


def env_settings_for(agent: str | None, config: str | None, system: str | None) -> dict[str, Any]:
    """The env settings policies play under: the trained agent's own (so its observation matches), else a
    config file's [env], else the defaults; ``system`` overrides the system under test."""
    from genesis_rl.config import read_toml

    env: dict[str, Any] = {}
    if agent:
        run = Path(agent)
        run_dir = run_folder_of(run)
        cfg_path = run_dir / "config.toml"
        if not run.exists():
            raise UserInputError(f"--agent '{agent}' does not exist")
        if not cfg_path.is_file():
            raise UserInputError(f"--agent '{agent}': no config.toml in '{run_dir}', so its env settings are unknown")
        env = dict(read_toml(cfg_path).get("env", {}))
    elif config:
        env = dict(read_toml(config).get("env", {}))
    if system:
        env["system"] = system
    for key in ("catalog", "scenes", "catalog_seed", "map", "episode_steps"):
        env.pop(key, None)  # the campaign decides these
    env["terminate_on_collision"] = False  # the protocol drives every episode for its full length
    return env


def check_spec(spec: CampaignSpec) -> None:
    """Everything that can be checked before a folder is touched: policies, their options, the agent."""
    from genesis_rl.evaluation.policies import load_agent

    if spec.steps < 1:
        raise UserInputError(f"--steps = {spec.steps} must be >= 1")
    if spec.records not in ("failures", "all"):
        raise UserInputError(f"records = '{spec.records}' is unknown; allowed: failures, all")
    for name in spec.policies:
        cls = resolve_policy(name)
        if cls.needs_agent and not spec.agent:
            raise UserInputError(f"policy '{name}' needs a trained agent: pass --agent runs/NAME")
        if not cls.needs_agent:
            cls(PolicyContext(action_dim=1, seed=spec.seed, options={**spec.options, "steps": spec.steps}))
    if any(resolve_policy(p).needs_agent for p in spec.policies):
        load_agent(Path(spec.agent) if spec.agent else None)


def campaign_identity(spec: CampaignSpec) -> dict[str, Any]:
    """What must not change between a campaign and its resumption besides the spec: the package version,
    the agent's file, the system under test (class, weights hash) and the rulebook's content (its rules
    and parameters, not its file's path). Summaries and reports read the rulebook from here."""
    from genesis_rl.evaluation.policies import agent_file
    from genesis_rl.perception.detector import file_sha256
    from genesis_rl.system.protocol import load_system

    found = agent_file(Path(spec.agent)) if spec.agent else None
    agent_sha = file_sha256(found) if found else None
    system = load_system(spec.env.get("system", "builtin"), **spec.env.get("system_kwargs", {}))
    rulebook_path = spec.env.get("rulebook")
    try:
        rulebook = load_rulebook(rulebook_path) if rulebook_path else default_rulebook()
    except UserInputError as err:
        raise UserInputError(f"env.rulebook: {err}") from None
    return {"package_version": __version__, "agent_sha256": agent_sha,
            "system": json.loads(json.dumps(system.identity(), default=str)),
            "rulebook": rulebook.describe()}


def prepare_campaign(spec: CampaignSpec, folder: Path, force: bool, resume: bool,
                     progress: bool = True) -> list[tuple[str, int, int]]:
    """Create (or reopen) the campaign folder; return the tasks still to run."""
    from genesis_rl.backends import catalog_or_generate
    from genesis_rl.io_utils import ensure_folder_path
    from genesis_rl.lite.scenes import DEFAULT_COUNTS

    check_spec(spec)
    ensure_folder_path(folder)
    meta = folder / "campaign.json"
    identity = campaign_identity(spec)
    if resume:
        if not meta.is_file():
            raise UserInputError(f"--resume: '{folder}' is not a campaign folder (no campaign.json)")
        saved = read_json(meta, "campaign file")
        saved_identity = saved.get("identity", {})
        # a key the campaign's version did not store (the rulebook before 0.5.0) cannot be compared
        changed = sorted(k for k in identity if k in saved_identity and saved_identity[k] != identity[k])
        if changed:
            raise UserInputError(f"--resume: {', '.join(changed)} changed since the campaign in '{folder}' began "
                                 "(results would mix); pass --force to start over")
        now = json.loads(json.dumps(spec.to_json()))
        # the agent is compared by its file's hash (in the identity above), not by how its path was spelled
        diff = sorted(k for k in now if k != "agent" and saved.get("spec", {}).get(k) != now[k])
        if diff:
            raise UserInputError(f"--resume: the campaign in '{folder}' was run with other settings "
                                 f"({', '.join(diff)}); pass the same arguments, or --force to start over")
        pairs = [tuple(p) for p in saved["scenes"]]
    else:
        output_folder.check_inputs(folder, [spec.catalog, spec.agent], nested_ok=True)  # RUN/eval is the default
        output_folder.check_target(folder, "campaign", force, resume_hint=True)
        count = DEFAULT_COUNTS.get(spec.map, 1)
        catalog = catalog_or_generate(spec.catalog, spec.map, count, spec.catalog_seed, progress=progress)
        pairs = pick_scenes(len(catalog.scenes), spec.scenes, spec.seed)
        output_folder.replace(folder, "campaign")
        catalog.save(folder / "catalog.json")
        from genesis_rl.training.train import git_commit

        atomic_write_json(meta, {"schema": CAMPAIGN_SCHEMA, "version": CAMPAIGN_VERSION, "package_version": __version__,
                                 "git_commit": git_commit(), "spec": spec.to_json(), "scenes": pairs,
                                 "identity": identity,
                                 "catalog": {"map": catalog.map, "seed": catalog.seed,
                                             "scenes": len(catalog.scenes)},
                                 "started": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=2)
    return [(p, s, e) for p in spec.policies for s, e in pairs
            if not (folder / "episodes" / p / f"{episode_name(s)}.json").is_file()]


def run_campaign(spec: CampaignSpec, folder: Path, workers: int = 1, force: bool = False, resume: bool = False,
                 progress: bool = True) -> dict[str, Any]:
    """Run every (policy, scene) not yet done, then write summary.json; returns the summary. The folder is
    held for the whole run: a second campaign into it is refused, not mixed in."""
    with output_folder.hold(folder):
        return _run_campaign(spec, folder, workers, force, resume, progress)


def _run_campaign(spec: CampaignSpec, folder: Path, workers: int, force: bool, resume: bool,
                  progress: bool) -> dict[str, Any]:
    from tqdm import tqdm

    from genesis_rl.evaluation.summary import summarize_campaign

    if workers < 1:
        raise UserInputError(f"--workers = {workers} must be >= 1")
    tasks = prepare_campaign(spec, folder, force, resume, progress)  # checks policies and agent first
    t0 = time.perf_counter()
    init_args = (spec.to_json(), str(folder), 1, plugin_modules())
    bar = tqdm(total=len(tasks), desc="evaluate", unit="episode", disable=not progress)
    try:
        if workers == 1 or len(tasks) <= 1:
            _worker_init(*init_args)
            try:
                for task in tasks:
                    row = run_task(task)
                    bar.set_postfix_str(f"{row['policy']} scene {row['scene']} coll={row['collision_events']}")
                    bar.update()
            finally:
                if _WORKER.get("runner") is not None:
                    _WORKER["runner"].close()
        else:
            import multiprocessing as mp

            ctx = mp.get_context("spawn")
            # longest tasks first (search baselines) so workers finish together; stable for equal costs
            tasks.sort(key=lambda t: -resolve_policy(t[0]).episodes_per_scene(spec.options))
            with ctx.Pool(min(workers, len(tasks)), initializer=_worker_init, initargs=init_args) as pool:
                for row in pool.imap_unordered(run_task, tasks):
                    bar.set_postfix_str(f"{row['policy']} scene {row['scene']} coll={row['collision_events']}")
                    bar.update()
    except BaseException:
        if not resume and not any((folder / "episodes").glob("*/*.json")):
            # no episode finished (e.g. the agent's env settings are invalid): leave no folder behind that a
            # corrected re-run would need --force to replace
            shutil.rmtree(folder, ignore_errors=True)
        raise
    finally:
        bar.close()
    summary = summarize_campaign(folder)
    summary["run_seconds"] = round(time.perf_counter() - t0, 1)
    summary["workers"] = workers
    atomic_write_text(folder / "run_time.json", json.dumps({"seconds": summary["run_seconds"], "workers": workers,
                                                           "episodes_run": len(tasks), "cpus": os.cpu_count()}))
    return summary


__all__ = ["CampaignSpec", "CampaignRunner", "FAILURE_MODES", "FailureModeThresholds", "pick_scenes",
           "prepare_campaign", "run_campaign", "env_settings_for"]
