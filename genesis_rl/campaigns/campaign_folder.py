"""A campaign's folder: created once, reopened to resume, never mixed.

Layout::

    campaign.json                    the spec, scenes, episode seeds, identity (version, agent and weights
                                     hashes, rulebook), git commit
    catalog.json                     the test catalog the scenes come from
    episodes/<policy>/scene_NNNN.json     one summary row per episode (written last: marks it done)
    steps/<policy>/scene_NNNN.parquet     every step: the flat columns of StepRecord
    frames/<policy>/scene_NNNN/step_NNNN.jpg  camera frames around the first collision
    records/<policy>_scene_NNNN.json      self-contained edge-case records (replayable)
    summary.json, episodes.csv            written by ``summary.summarize_campaign``

Resuming checks that nothing deciding the results changed (spec, package version, agent and weights
hashes, the rulebook's content, catalog.json's hash) and runs again every episode that is missing or whose
files are damaged.
Reading the files is ``campaign_files``' job.
"""

from __future__ import annotations

import json
import shutil
import time
import warnings
from pathlib import Path
from typing import Any

from genesis_rl import __version__
from genesis_rl.adversaries import agent_file
from genesis_rl.campaigns.campaign_files import (
    CAMPAIGN_SCHEMA,
    CAMPAIGN_VERSION,
    env_named_files,
    episode_name,
    episode_path,
    read_episode_row,
    read_steps,
    steps_path,
)
from genesis_rl.campaigns.campaign_spec import CampaignSpec, check_spec, pick_scenes
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.hashing import file_sha256
from genesis_rl.core.files.io_utils import atomic_write_json, ensure_folder_path
from genesis_rl.core.parsing import read_json
from genesis_rl.core.provenance import git_commit
from genesis_rl.core.signals import deferred_signals
from genesis_rl.loop.rules.rulebook import rulebook_for
from genesis_rl.sim.backends import catalog_or_generate
from genesis_rl.sim.lite.scenes import DEFAULT_COUNTS
from genesis_rl.sut.system.protocol import load_system
from genesis_rl.world.odd.domain import load_odd

Task = tuple[str, int, int]  # (policy, scene, episode seed)


def campaign_identity(spec: CampaignSpec) -> dict[str, Any]:
    """What must not change between a campaign and its resumption besides the spec: the package version,
    the agent's file, the system under test (class, weights hash) and the rulebook's content (its rules
    and parameters, not its file's path). Summaries and reports read the rulebook from here."""
    found = agent_file(Path(spec.agent)) if spec.agent else None
    agent_sha = file_sha256(found) if found else None
    system = load_system(spec.env.get("system", "builtin"), **spec.env.get("system_kwargs", {}))
    try:
        rulebook = rulebook_for(spec.env.get("rulebook"), with_odd=spec.env.get("odd") is not None)
    except UserInputError as err:
        raise UserInputError(f"env.rulebook: {err}") from None
    identity = {"package_version": __version__, "agent_sha256": agent_sha,
                "system": json.loads(json.dumps(system.identity(), default=str)),
                "rulebook": rulebook.describe()}
    if spec.env.get("odd"):  # the domain's content: a campaign keeps meaning what it meant if the file changes
        identity["odd"] = load_odd(spec.env["odd"]).describe()
    return identity


def spec_differences(saved: Any, spec: CampaignSpec) -> list[str]:
    """The settings in which a campaign.json's ``spec`` differs from ``spec`` (the agent is compared by its
    file's hash, in the identity, not by how its path was spelled)."""
    now = json.loads(json.dumps(spec.to_json()))
    saved = saved if isinstance(saved, dict) else {}
    return sorted(k for k in now if k != "agent" and saved.get(k) != now[k])


def check_finished_campaign(spec: CampaignSpec, folder: Path) -> None:
    """A finished campaign that a resumed benchmark or sweep keeps must be the one it would run: an edited
    ``spec`` (a policy dropped, other scenes) would silently change the leaderboard, and so would an edited
    ``scenes`` list (other episode seeds) or catalog."""
    from genesis_rl.campaigns.campaign_files import read_campaign_meta

    meta = read_campaign_meta(folder)
    diff = spec_differences(meta["spec"], spec)
    if diff:
        raise UserInputError(f"--resume: '{CampaignFolder(folder).meta}' holds other settings than this trial's "
                             f"({', '.join(diff)}): it was edited, or belongs to another run; delete the folder "
                             f"'{folder}' (it runs again) or start over with --force")
    _check_catalog_pin(folder, meta.get("catalog"))
    _check_scene_pairs(folder, meta, spec, [tuple(p) for p in meta["scenes"]])


def prepare_campaign(spec: CampaignSpec, folder: Path, force: bool, resume: bool,
                     progress: bool = True) -> list[Task]:
    """Create (or reopen) the campaign folder; return the tasks still to run."""
    check_spec(spec)
    ensure_folder_path(folder)
    meta = CampaignFolder(folder).meta
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
        diff = spec_differences(saved.get("spec", {}), spec)
        if diff:
            raise UserInputError(f"--resume: the campaign in '{folder}' was run with other settings "
                                 f"({', '.join(diff)}); pass the same arguments, or --force to start over")
        _check_catalog_pin(folder, saved.get("catalog"))
        pairs = [tuple(p) for p in saved["scenes"]]
        _check_scene_pairs(folder, saved, spec, pairs)
    else:
        # RUN/eval is the default folder, inside the run it plays
        output_folder.check_folder_inputs(folder, [spec.catalog, spec.agent, *env_named_files(spec.env)],
                                          nested_ok=True)
        output_folder.check_target(folder, "campaign", force, resume_hint=True)
        count = DEFAULT_COUNTS.get(spec.map, 1)
        catalog = catalog_or_generate(spec.catalog, spec.map, count, spec.catalog_seed, progress=progress,
                                      traffic=spec.traffic)
        if catalog.map != spec.map:  # the campaign records spec.map: it must be the map its scenes are on
            raise UserInputError(f"map '{spec.map}' and catalog '{spec.catalog}' disagree: the catalog's scenes are on "
                                 f"map '{catalog.map}'; pass --map {catalog.map}, or a catalog made for '{spec.map}'")
        pairs = pick_scenes(len(catalog.scenes), spec.scenes, spec.seed, spec.exclude)
        commit = git_commit()
        with deferred_signals():  # the folder with its catalog and campaign.json, so --resume can take it up
            output_folder.replace(folder, "campaign")
            catalog.save(CampaignFolder(folder).catalog)
            atomic_write_json(meta, {"schema": CAMPAIGN_SCHEMA, "version": CAMPAIGN_VERSION,
                                     "package_version": __version__, "git_commit": commit, "spec": spec.to_json(),
                                     "scenes": pairs, "identity": identity,
                                     "catalog": {"map": catalog.map, "seed": catalog.seed,
                                                 "scenes": len(catalog.scenes),
                                                  "sha256": file_sha256(CampaignFolder(folder).catalog)},
                                     "started": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=2)
    return [(p, s, e) for p in spec.policies for s, e in pairs if not episode_done(folder, p, s, resume)]


def _check_catalog_pin(folder: Path, saved: Any) -> None:
    """The scenes of a resumed campaign come from its catalog.json: it must be the file the campaign began
    with (campaigns of genesis-rl 0.10.0 and earlier recorded no hash: not checked)."""
    pinned = saved.get("sha256") if isinstance(saved, dict) else None
    if pinned is None:
        return
    path = CampaignFolder(folder).catalog
    found = file_sha256(path) if path.is_file() else None
    if found != pinned:
        raise UserInputError(f"--resume: '{path}' {'changed' if found else 'is missing'} since the campaign began "
                             f"(campaign.json pins sha256 {str(pinned)[:16]}, found {(found or 'none')[:16]}): the "
                             "remaining episodes would play other scenes; restore it, or pass --force to start over")


def _check_scene_pairs(folder: Path, saved: dict, spec: CampaignSpec, pairs: list[tuple]) -> None:
    """The scenes and episode seeds a campaign.json lists are those its seed draws from its catalog: an edited
    list would resume other episodes under the campaign's name (results would mix)."""
    size = (saved.get("catalog") or {}).get("scenes")
    if type(size) is not int:  # campaigns of 0.4.0 kept no catalog size: nothing to redraw from
        return
    expected = [tuple(p) for p in pick_scenes(size, spec.scenes, spec.seed, spec.exclude)]
    if pairs != expected:
        raise UserInputError(f"--resume: '{folder / 'campaign.json'}' field 'scenes' is not what seed {spec.seed} "
                             f"draws from its {size}-scene catalog (scene indices or episode seeds were edited); "
                             "restore the file, or pass --force to start over")


def episode_done(folder: Path, policy: str, scene: int, resume: bool) -> bool:
    """Whether an episode's files are all there and sound. On resume, a damaged episode (its row or its steps
    unreadable, e.g. a disk filled up or a file was edited) is set aside under ``damaged/`` and run again."""
    row_path = episode_path(folder, policy, scene)
    if not row_path.is_file():
        return False
    if not resume:
        return True
    try:
        row = read_episode_row(row_path)
        # as many step rows as the row states, from the footer: a file of another episode (or a crafted one
        # claiming millions of rows) is set aside before any row is read
        read_steps(steps_path(folder, policy, scene), columns=["step"], steps=row["steps"])
        return True
    except UserInputError as err:
        aside = folder / "damaged" / time.strftime("%Y%m%d-%H%M%S") / policy
        aside.mkdir(parents=True, exist_ok=True)
        for path in (row_path, steps_path(folder, policy, scene)):
            if path.exists():
                shutil.move(str(path), aside / path.name)
        warnings.warn(f"{policy} {episode_name(scene)} is damaged ({err}); it is run again (the damaged files "
                      f"are kept in '{aside}')", stacklevel=2)
        return False
