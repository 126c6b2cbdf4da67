"""Edge-case records: a failing episode, self-contained, and its exact replay.

A record holds everything that decides the episode: the scene itself (not a pointer into a catalog), the
episode seed, the weather of every step, the system's identity (class, weights hash) and settings, the
camera, the rulebook and the backend with its version. ``replay_record`` drives it again on ``lite`` and
checks that every rule's violation comes out the same.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from genesis_rl import __version__
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import atomic_write_json
from genesis_rl.core.parsing import read_json
from genesis_rl.core.provenance import numeric_platform
from genesis_rl.loop.drive import ClosedLoop
from genesis_rl.loop.rules.rulebook import build_rulebook
from genesis_rl.sim.backends import catalog_from_json
from genesis_rl.sim.interface import EXPOSURE_JITTER_MAX, CameraConfig, Simulation
from genesis_rl.sim.lite.backend import LiteBackend
from genesis_rl.sut.perception.detector import archived_weights
from genesis_rl.sut.system.protocol import load_system
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.step_record import RULE_PREFIX, StepRecord

RECORD_SCHEMA = "genesis-rl/edge-case"
RECORD_VERSION = 1


DIGEST_FIELDS = ("step", "ego_speed", "throttle", "brake", "steer", "true_lead_distance", "perceived_lead_distance",
                 "iou", "collision", "collision_speed", "detections")


def step_digest(records: Sequence[StepRecord]) -> str:
    """SHA-256 over every step's state, controls, detections and rule terms: replay must match it bit for
    bit, not only in the summed violations."""
    h = hashlib.sha256()
    for rec in records:
        r = rec.to_row()
        row = {k: r[k] for k in DIGEST_FIELDS}
        row.update({k: v for k, v in r.items() if k.startswith(RULE_PREFIX)})
        h.update(json.dumps(row, sort_keys=True, default=str).encode())
    return h.hexdigest()


def make_record(spec: Any, runner: Any, policy: str, scene: int, episode_seed: int,
                records: Sequence[StepRecord], row: dict[str, Any], start: Weather | None = None) -> dict[str, Any]:
    """The record of one episode played by a ``CampaignRunner``. It carries its knob set (``knobs``): a
    record written before a knob existed replays with that knob at its default; and the weather the episode
    started from (``start``; None: the env's start weather), so a replay starts there too."""
    env = runner.env
    cfg = env.config
    sc = env.catalog.scene(scene)
    return {
        "schema": RECORD_SCHEMA, "version": RECORD_VERSION,
        "package_version": __version__, "backend": env.backend.name,
        "render_version": getattr(env.backend, "render_version", None),
        "platform": numeric_platform(),
        "policy": policy, "campaign_seed": spec.seed,
        "scene": {"index": sc.index, "map": sc.map, "seed": sc.seed, "signal_offset": sc.signal_offset,
                  "vehicles": [asdict(v) for v in sc.vehicles]},
        "catalog": {"map": env.catalog.map, "seed": env.catalog.seed, "index": scene},
        "episode_seed": episode_seed,
        "world_seed": env.world_seed,
        "steps": len(records),
        "camera": {"width": cfg.camera_width, "height": cfg.camera_height,
                   **({"exposure_jitter": cfg.camera_exposure_jitter} if cfg.camera_exposure_jitter else {})},
        "system": {"spec": cfg.system, "kwargs": cfg.system_kwargs, "identity": env.system.identity()},
        "rulebook": env.rulebook.describe(),
        "start_weather": (start or env.start_weather).as_dict(),
        "knobs": list(KNOBS),
        "schedule": [[r.knobs[k] for k in KNOBS] for r in records],
        "violations": env.rulebook.violations(records),
        "step_digest": step_digest(records),
        "failure": row["failure"],
        "summary": {**{k: row[k] for k in env.rulebook.names},
                    **{k: row[k] for k in ("collision_events", "first_collision_step", "failure_mode", "mean_iou")}},
    }


def save_record(path: Path, record: dict[str, Any]) -> None:
    atomic_write_json(path, record)


def load_record(path: Path | str) -> dict[str, Any]:
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"record '{path}' is a folder; expected a record file (CAMPAIGN/records/*.json)")
    if not path.is_file():
        raise UserInputError(f"record '{path}' does not exist")
    rec = read_json(path, "record")
    if not isinstance(rec, dict) or rec.get("schema") != RECORD_SCHEMA:
        raise UserInputError(f"'{path}' is not a GENESIS-RL edge-case record (schema {RECORD_SCHEMA})")
    if type(rec.get("version")) is not int or rec["version"] != RECORD_VERSION:  # JSON's true == 1 in Python
        raise UserInputError(f"record '{path}' has schema version {rec.get('version')}; this genesis-rl "
                             f"{__version__} replays version {RECORD_VERSION}")
    missing = [k for k in ("scene", "episode_seed", "schedule", "knobs", "start_weather", "system", "rulebook",
                           "camera", "violations") if k not in rec]
    if missing:
        raise UserInputError(f"record '{path}' lacks field(s) {missing}")
    _check_record(rec, path)
    return rec


def _check_record(rec: dict[str, Any], path: Path) -> None:
    """The fields replay builds a simulation from, with their types and ranges: a hand-edited record fails
    here, naming the field, not deep inside the simulator."""
    def bad(field: str, allowed: str) -> UserInputError:
        return UserInputError(f"record '{path}': field '{field}' = {str(rec_get(field))[:60]!r}; allowed: {allowed}")

    def rec_get(field: str) -> Any:
        value: Any = rec
        for part in field.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        return value

    for field in ("scene", "system", "camera", "violations", "start_weather"):
        if not isinstance(rec.get(field), dict):
            raise bad(field, "an object")
    if not isinstance(rec.get("rulebook"), list | dict):
        raise bad("rulebook", "the recorded list of rules")
    for field in ("system.kwargs", "system.identity"):  # dict() of a list of pairs would misread, not refuse
        if not isinstance(rec_get(field) or {}, dict):
            raise bad(field, "an object")
    for field in ("camera.width", "camera.height"):
        v = rec_get(field)
        if isinstance(v, bool) or not isinstance(v, int) or not 16 <= v <= 4096:
            raise bad(field, "an integer in 16..4096")
    jitter = rec_get("camera.exposure_jitter") or 0.0  # absent in records before it and without one
    if isinstance(jitter, bool) or not isinstance(jitter, int | float) or not 0.0 <= jitter <= EXPOSURE_JITTER_MAX:
        raise bad("camera.exposure_jitter", f"a number in 0..{EXPOSURE_JITTER_MAX}")
    for field in ("episode_seed", "world_seed"):  # world_seed: absent in records before it (the episode seed)
        seed = rec.get(field, 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise bad(field, "an integer >= 0")
    knobs = rec.get("knobs")
    if not isinstance(knobs, list) or not knobs or not all(k in KNOBS for k in knobs):
        raise bad("knobs", f"a list of knob names from {', '.join(KNOBS)}")
    schedule = rec.get("schedule")
    if not isinstance(schedule, list) or not schedule:
        raise bad("schedule", f"a list of rows, one per step, each {len(knobs)} numbers")
    for i, row in enumerate(schedule):
        if (not isinstance(row, list) or len(row) != len(knobs)
                or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in row)):
            raise bad(f"schedule[{i}]", f"{len(knobs)} numbers ({', '.join(knobs)})")
        for k, v in zip(knobs, row, strict=True):
            spec = KNOBS[k]
            if not spec.low <= v <= spec.high:
                raise UserInputError(f"record '{path}': schedule[{i}] {k} = {v}; allowed {spec.low:g}..{spec.high:g}")
    steps = rec.get("steps", len(schedule))
    if isinstance(steps, bool) or not isinstance(steps, int) or steps != len(schedule):
        raise bad("steps", f"the schedule's length, {len(schedule)}")
    if rec.get("step_digest") is not None and not isinstance(rec["step_digest"], str):
        raise bad("step_digest", "a hex string or null")
    for k, v in rec["violations"].items():
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise bad(f"violations.{k}", "a number")


def load_recorded_system(recorded: dict[str, Any], weights: str | None = None, where: str = "the record") -> Any:
    """The system a record names (``{"spec", "kwargs", "identity"}``), with the weights it was made with: the
    given ``weights``, else the record's own, else the shipped archive's copy with the recorded sha256.
    Refuses weights whose sha256 differs from the recorded one; ``where`` names the record in errors."""
    if not isinstance(recorded, dict):
        raise UserInputError(f"{where}: field 'system' = {str(recorded)[:60]!r}; allowed: an object")
    for field in ("kwargs", "identity"):
        if not isinstance(recorded.get(field) or {}, dict):
            raise UserInputError(f"{where}: field 'system.{field}' = {str(recorded[field])[:60]!r}; allowed: an "
                                 "object")
    kwargs = dict(recorded.get("kwargs") or {})
    recorded_id = recorded.get("identity") or {}
    if weights:
        kwargs["weights"] = weights
    elif "weights" not in kwargs and recorded_id.get("weights_sha256"):
        shipped = archived_weights(recorded_id["weights_sha256"])  # an older record: the weights it was made with
        if shipped is not None:
            kwargs["weights"] = str(shipped)
    system = load_system(recorded["spec"], **kwargs)
    now_id = system.identity()
    if recorded_id.get("weights_sha256") and recorded_id.get("weights_sha256") != now_id.get("weights_sha256"):
        raise UserInputError(f"the record's system used weights sha256 {recorded_id['weights_sha256'][:12]}…, "
                             f"these are {str(now_id.get('weights_sha256'))[:12]}…; pass --weights with the "
                             "recorded file to replay it")
    return system


def recorded_world_seed(rec: dict[str, Any]) -> int:
    """The world seed the recorded episode ran in (records before the field: its episode seed)."""
    return int(rec.get("world_seed", rec["episode_seed"]))


def replay_record(rec: dict[str, Any], weights: str | None = None, progress: bool = False,
                  keep_frames: bool = True, observer: Callable[[Simulation], None] | None = None,
                  world_seed: int | None = None) -> dict[str, Any]:
    """Drive the record's episode again; returns the step records, frames, violations and whether they
    equal the recorded ones (to 1e-9). ``observer`` sees the simulation after the start and after every step
    (the OpenSCENARIO export reads every vehicle's pose there). ``world_seed``: play the recorded schedule in
    another world (the traffic's behaviour, the camera's noise, the system's draws), as the benchmark's re-runs
    do; None: the recorded world."""
    import torch  # local: start-up cost

    if rec.get("backend", "lite") != "lite":
        raise UserInputError(f"record backend '{rec['backend']}': replay runs on lite only for now")
    torch.set_num_threads(1)  # campaigns run the detector on one thread; the same arithmetic replays exactly
    catalog = catalog_from_json({"schema": "genesis-rl/scene-catalog", "version": 1, "backend": "lite",
                                 "map": rec["scene"]["map"], "seed": rec["catalog"]["seed"],
                                 "scenes": [rec["scene"]]})
    scene = catalog.scenes[0]
    rulebook = build_rulebook(rec["rulebook"], "record rulebook")  # refuses import paths before any system loads
    system = load_recorded_system(rec["system"], weights)
    now_id = system.identity()
    names = rec["knobs"]
    start = Weather.from_recorded(rec["start_weather"])
    camera = CameraConfig(width=rec["camera"]["width"], height=rec["camera"]["height"],
                          exposure_jitter=rec["camera"].get("exposure_jitter", 0.0))
    backend = LiteBackend()
    records: list[StepRecord] = []
    frames: list[np.ndarray] = []
    try:
        world = recorded_world_seed(rec) if world_seed is None else int(world_seed)
        with backend.create_simulation(scene, seed=world, weather=start, camera=camera) as sim:
            loop = ClosedLoop(sim, system, backend.name, world)
            loop.start(start)
            if observer is not None:
                observer(sim)
            for row in tqdm(rec["schedule"], desc="replay", unit="step", disable=not progress):
                r = loop.advance(Weather.from_recorded(dict(zip(names, row, strict=True))))
                records.append(r.scored(rulebook.step_terms(r)))
                if observer is not None:
                    observer(sim)
                if keep_frames:
                    assert loop.frame is not None
                    frames.append(loop.frame.rgb)
    finally:
        backend.close()
    violations = rulebook.violations(records)
    recorded = rec["violations"]
    recorded_render = rec.get("render_version", 1)  # records before the field were made by version 1
    digest = step_digest(records)
    same_steps = rec.get("step_digest") in (None, digest)
    reproduced = same_steps and set(violations) == set(recorded) and all(
        math.isclose(violations[k], recorded[k], rel_tol=1e-9, abs_tol=1e-9) for k in recorded)
    return {"records": records, "frames": frames, "violations": violations, "recorded_violations": recorded,
            "reproduced": reproduced, "steps_identical": same_steps, "step_digest": digest, "identity": now_id,
            "render_version": LiteBackend.render_version, "recorded_render_version": recorded_render,
            "platform": numeric_platform(), "recorded_platform": rec.get("platform")}
