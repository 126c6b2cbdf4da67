"""Reading a campaign folder's files, and telling damage from bugs.

Every file a campaign wrote is parsed here (``campaign.json``, episode rows, step Parquet, kept frames), and
only here is a malformed file turned into a user error: it names the file, what is wrong in it, and what to
do (``evaluate --resume`` runs damaged episodes again). Code that works on parsed data (summaries, the report,
the export) raises its own errors as they are, so a bug is never reported as a damaged file.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.layout import CampaignFolder, episode_name  # noqa: F401  (episode_name: read here)
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.parsing import read_json
from genesis_rl.world.step_record import StepRecord, from_rows

CAMPAIGN_SCHEMA = "genesis-rl/campaign"
CAMPAIGN_VERSION = 1
#: what to do about a damaged file in a campaign folder
REMEDY = ("delete it and run genesis-rl evaluate --resume with the campaign's arguments (damaged episodes run "
          "again), or start over with --force")


def episode_path(folder: Path, policy: str, scene: int) -> Path:
    return CampaignFolder(folder).episode(policy, scene)


def steps_path(folder: Path, policy: str, scene: int) -> Path:
    return CampaignFolder(folder).steps(policy, scene)


def _damaged(path: Path, what: str) -> UserInputError:
    return UserInputError(f"'{path}' is damaged: {what}; {REMEDY}")


#: seeds and scene indices: numpy refuses negative seeds (with a traceback); 64-bit as TOML's integers
_SEEDS = (0, 2**63 - 1)


def env_named_files(env: Any) -> list[str]:
    """The files an env's settings name (catalog, ODD, rulebook, detector weights, and every string in
    ``system_kwargs`` that names a file): a command writing onto one of them would destroy what it reads."""
    if not isinstance(env, dict):
        return []
    named = [v for k in ("catalog", "odd", "rulebook", "weights") if isinstance(v := env.get(k), str) and v]
    kwargs = env.get("system_kwargs")
    if isinstance(kwargs, dict):
        named += [v for v in kwargs.values() if isinstance(v, str) and v and Path(v).exists()]
    return named


def campaign_named_files(folder: Path) -> list[str]:
    """What a campaign reads besides its own folder: its agent run (or .zip), its catalog and the files its
    env names. An unreadable campaign names nothing (the command reading it will say why)."""
    try:
        spec = read_campaign_meta(folder)["spec"]
    except UserInputError:
        return []
    named = [v for v in [spec.get("catalog")] if isinstance(v, str) and v]
    agent = spec.get("agent")
    if isinstance(agent, str) and agent:
        # a run folder: the files the agent is read from (a campaign at RUN/eval lies inside it by design)
        named += [str(Path(agent) / f) for f in AGENT_RUN_FILES] if Path(agent).is_dir() else [agent]
    return named + env_named_files(spec.get("env"))


#: what playing a run folder's agent reads from it
AGENT_RUN_FILES = ("agent.zip", "checkpoints/last.zip", "config.toml", "run.json", "catalog.json")


def read_campaign_meta(folder: Path) -> dict[str, Any]:
    """``campaign.json``, checked for the fields that summaries, reports, exports and resumption read."""
    folder = Path(folder)
    path = CampaignFolder(folder).meta
    if not folder.exists():
        raise UserInputError(f"campaign folder '{folder}' does not exist")
    if not folder.is_dir():
        raise UserInputError(f"'{folder}' is a file; expected a campaign folder (genesis-rl evaluate --out)")
    if not path.is_file():
        raise UserInputError(f"'{folder}' is not a campaign folder (no campaign.json); run genesis-rl evaluate first")
    meta = read_json(path, "campaign file")
    if not isinstance(meta, dict):
        raise _damaged(path, f"expected a JSON object, found {type(meta).__name__}")
    if meta.get("schema") != CAMPAIGN_SCHEMA or not _is_int(meta.get("version")) or meta["version"] != CAMPAIGN_VERSION:
        raise UserInputError(f"'{path}' has schema {meta.get('schema')} version {meta.get('version')}; "
                             f"this genesis-rl reads {CAMPAIGN_SCHEMA} version {CAMPAIGN_VERSION}")
    spec = meta.get("spec")
    if not isinstance(spec, dict):
        raise _damaged(path, "field 'spec' is missing or not an object")
    policies = spec.get("policies")
    if not isinstance(policies, list) or not policies or not all(isinstance(p, str) and p for p in policies):
        raise _damaged(path, f"field 'spec.policies' = {policies!r}; expected a list of policy names")
    for key, (low, high) in (("seed", _SEEDS), ("steps", (1, 2**31 - 1))):
        if not _is_int(spec.get(key)) or not low <= spec[key] <= high:
            raise _damaged(path, f"field 'spec.{key}' = {str(spec.get(key))[:30]}; expected an integer in "
                                 f"{low}..{high}")
    scenes = meta.get("scenes")
    if not isinstance(scenes, list) or not all(isinstance(p, list) and len(p) == 2 and all(map(_is_int, p))
                                                 and all(_SEEDS[0] <= v <= _SEEDS[1] for v in p) for p in scenes):
        raise _damaged(path, "field 'scenes' must be a list of [scene index, episode seed] pairs (integers in "
                             f"{_SEEDS[0]}..{_SEEDS[1]})")
    return meta


#: Fields of an episode row that later stages read, with the check each must pass.
_ROW_FIELDS: dict[str, tuple[str, Any]] = {
    "scene": ("an integer", lambda v: _is_int(v)),
    "episode_seed": ("an integer", lambda v: _is_int(v)),
    "steps": ("an integer", lambda v: _is_int(v)),
    "total": ("a number", lambda v: _is_number(v)),
    "collision_events": ("an integer", lambda v: _is_int(v)),
    "first_collision_step": ("an integer or null", lambda v: v is None or _is_int(v)),
    "failure_mode": ("a failure mode or null", lambda v: v is None or isinstance(v, str)),
    "mean_iou": ("a number or null", lambda v: v is None or _is_number(v)),
    "return": ("a number", lambda v: _is_number(v)),
    "collision_speed": ("a number", lambda v: _is_number(v)),
    "min_gap": ("a number or null", lambda v: v is None or _is_number(v)),
    "sim_steps": ("an integer", lambda v: _is_int(v)),
}


def read_episode_row(path: Path) -> dict[str, Any]:
    """One episode's summary row, checked field by field (every rule's violation among them)."""
    row = read_json(path, "episode file")
    if not isinstance(row, dict):
        raise _damaged(path, f"expected a JSON object, found {type(row).__name__}")
    violations = row.get("violations")
    if not isinstance(violations, dict) or not violations:
        raise _damaged(path, "field 'violations' is missing or empty; expected every rule's violation")
    for name, value in violations.items():
        if not _is_number(value) or value < 0:
            raise _damaged(path, f"field 'violations.{name}' = {value!r}; expected a number >= 0")
        if row.get(name) != value:
            raise _damaged(path, f"field '{name}' = {row.get(name)!r} disagrees with violations.{name} = {value!r}")
    for name, (expected, ok) in _ROW_FIELDS.items():
        if name not in row or not ok(row[name]):
            raise _damaged(path, f"field '{name}' = {row.get(name, '(missing)')!r}; expected {expected}")
    _check_actor_events(path, row.get("actor_events"))
    return row


#: the fields of an actor event (``sim.interface.ActorEvent.as_dict``): what each must hold, and whether every
#: event has it
_EVENT_FIELDS: dict[str, tuple[str, Any, bool]] = {
    "kind": ("a string", lambda v: isinstance(v, str), True),
    "vehicle_id": ("an integer", lambda v: _is_int(v), True),  # lambdas: the helpers are defined below
    "onset_s": ("a number", lambda v: _is_number(v), True),
    **{k: ("a number or null", lambda v: v is None or _is_number(v), False)
       for k in ("perceivable_s", "ttc_s", "gap_m", "closing_m_s", "perceived_ttc_s")},
}


def _check_actor_events(path: Path, events: Any) -> None:
    """An episode row's ``actor_events`` (absent in campaigns before actor knobs), field by field: the
    summaries, the report and the blame read them as numbers."""
    if events is None:
        return
    if not isinstance(events, list):
        raise _damaged(path, f"field 'actor_events' = {events!r}; expected a list of events")
    for i, e in enumerate(events):
        if not isinstance(e, dict):
            raise _damaged(path, f"field 'actor_events[{i}]' = {e!r}; expected an object")
        for name, (expected, ok, required) in _EVENT_FIELDS.items():
            if (required and name not in e) or (name in e and not ok(e[name])):
                raise _damaged(path, f"field 'actor_events[{i}].{name}' = {e.get(name, '(missing)')!r}; "
                                     f"expected {expected}")


def read_steps(path: Path, columns: list[str] | None = None, steps: int | None = None) -> list[dict[str, Any]]:
    """An episode's step Parquet as rows (all columns, or ``columns`` that it has); ``steps``: the step count its
    episode row states, which the file's rows must equal (checked from the footer, before any row is read)."""
    import pyarrow as pa  # local: start-up cost
    import pyarrow.parquet as pq

    path = Path(path)
    if not path.is_file():
        raise UserInputError(f"steps file '{path}' is missing; {REMEDY}")
    try:
        # opened by Python, not by Arrow: Arrow cannot take a folder name that is not UTF-8
        with open(path, "rb") as fh:
            parquet = pq.ParquetFile(fh)
            rows = parquet.metadata.num_rows  # the footer's count, read before any row
            most = limits.SIM_STEPS.value() + 1  # an episode's steps and its start
            if rows > most:
                raise _damaged(path, f"it claims {rows:,} step rows; an episode has at most {most:,} "
                                     f"({limits.SIM_STEPS.variable} raises the limit)")
            if steps is not None and rows != steps:
                raise _damaged(path, f"it holds {rows:,} step rows where its episode row says {steps:,} steps")
            if columns is not None:
                present = set(parquet.schema_arrow.names)
                columns = [c for c in columns if c in present]
            return parquet.read(columns=columns).to_pylist()
    except (pa.ArrowException, OSError) as err:  # a truncated or foreign file
        raise _damaged(path, f"not a readable Parquet file ({err})") from None


def read_step_records(path: Path, steps: int | None = None) -> list[StepRecord]:
    """An episode's step Parquet as typed step records (``steps``: as ``read_steps``)."""
    rows = read_steps(path, steps=steps)
    try:
        return from_rows(rows)
    except (KeyError, TypeError, ValueError) as err:
        raise _damaged(path, f"a step row lacks or mangles column {err}") from None


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
