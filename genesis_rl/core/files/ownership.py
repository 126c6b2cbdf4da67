"""Which files of an output folder are genesis-rl's: the folder's kind (its marker), the names each kind writes,
the manifest of hashes (``manifest.py``) and whether the last writer was killed holding the folder.

``output_folder`` (claiming, replacing and holding folders) and ``output_paths`` (one-file outputs) both ask
this module; it asks neither, so the two can use it without importing each other.
"""

from __future__ import annotations

import fcntl
import os
import re
from dataclasses import dataclass
from pathlib import Path

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import manifest
from genesis_rl.core.parsing import read_json

MARKER = ".genesis-rl.json"
MARKER_SCHEMA = "genesis-rl/output-folder"
KINDS = ("run", "campaign", "export", "drive", "render", "benchmark", "sweep", "estimate", "harden")
#: kinds that continue with --resume (the refusal to overwrite one says so)
RESUMABLE = ("run", "campaign", "benchmark", "sweep", "estimate", "harden")
#: kinds whose folder is one unit that --force replaces whole; drive and render write named files into theirs
WHOLE_FOLDER = ("run", "campaign", "export", "benchmark", "sweep", "estimate", "harden")

#: the marker and the manifest (core/files/manifest.py): every kind's own
_BOOKKEEPING = (r"\.genesis-rl\.json", r"\.genesis-rl\.manifest\.json")
#: what genesis-rl itself writes at the top of a run, campaign or export folder (regular expressions on the
#: entry's name; a folder named here, e.g. checkpoints/, is the tool's as a whole). ``--force`` replaces a folder
#: only when it holds nothing else, and removes only these: a user's notes, or a campaign kept in a run folder
#: (RUN/eval), are named and kept. Temporaries of the atomic writes (".NAME.XXXXXXXX...") are the tool's too.
#: Names are the first test only: where the folder has a manifest, a file must also be listed there with the
#: same SHA-256 (``foreign_entries``).
OWN_ENTRIES: dict[str, tuple[str, ...]] = {
    "run": (*_BOOKKEEPING, r"agent\.zip", r"catalog\.json", r"checkpoints", r"config\.toml",
            r"episodes\.csv", r"run\.json", r"tb", r"train_result\.json"),
    "campaign": (*_BOOKKEEPING, r"campaign\.json", r"catalog\.json", r"episodes", r"steps", r"frames",
                 r"records", r"damaged", r"episodes\.csv", r"summary\.json", r"run_time\.json",
                 r"report[\w.-]*\.html", r"reactivity_[\w.-]*\.json"),
    "export": (*_BOOKKEEPING, r"images", r"labels", r"data\.yaml", r"annotations\.json",
               r"metadata\.jsonl", r"export\.json", r"scenarios", r"scenarios\.json"),
    "benchmark": (*_BOOKKEEPING, r"benchmark\.json", r"campaigns", r"leaderboard\.json",
                  r"leaderboard\.html", r"reproductions"),
    "sweep": (*_BOOKKEEPING, r"sweep\.json", r"sweep\.png", r"campaigns"),
    "estimate": (*_BOOKKEEPING, r"estimate\.json", r"estimate\.png", r"episodes\.csv", r"catalog\.json",
                 r"pins\.json"),
    "harden": (*_BOOKKEEPING, r"harden\.json", r"harden\.png", r"harden\.html", r"original_data\.npz",
               r"validation_data\.npz", r"pins\.json",
               r"round_\d+", r"final_attack", r"final_agent", r"retrained_attack",
               r"final_estimate", r"retest_\d+"),
}


#: inside the folders genesis-rl fills itself, the paths (relative to that folder) of the files it writes there:
#: ``--force`` names anything else it finds below them and refuses, so a user's notes in RUN/checkpoints/ or an
#: analysis in CAMPAIGN/records/ are never deleted with the folder
OWN_FILES: dict[tuple[str, str], str] = {
    ("run", "checkpoints"): r"step_\d{8}\.(zip|sb3\.npz|state\.json|replay\.npz|replay\.pkl)|last\.(zip|json)",
    ("run", "tb"): r"(\w+_\d+/)?events\.out\.tfevents\.[^/]+|progress\.csv",
    ("campaign", "episodes"): r"[^/]+/scene_\d{4}\.json",
    ("benchmark", "reproductions"): r"\w+/[\w.-]+\.json",
    ("campaign", "steps"): r"[^/]+/scene_\d{4}\.parquet",
    ("campaign", "frames"): r"[^/]+/scene_\d{4}/step_\d{4}\.jpg",
    ("campaign", "records"): r"[^/]+_scene_\d{4}\.json",
    ("export", "images"): r"[^/]+_scene\d{4}_step\d{4}\.jpg",
    ("export", "labels"): r"[^/]+_scene\d{4}_step\d{4}\.txt",
    ("export", "scenarios"): r"[^/]+\.(xosc|xodr)",
}


#: in a folder judged by names alone (one of 0.30.0, which kept no manifest): what harden, benchmark and sweep
#: write in their own folders outside the genesis-rl folders they nest there (campaigns, exports, estimates and
#: runs, each with its marker, judged by its own kind's names). Anything else below those folders is a user's:
#: a note in HARDEN/round_1/ is named and kept, not deleted with the round.
NESTED_OWN_FILES: dict[str, re.Pattern[str]] = {
    "harden": re.compile(r"round_\d+/round\.json|round_\d+/(weights|near_misses)/.+"),
    "benchmark": re.compile(r"(?!)"),  # campaigns/MEMBER/trial_NN are campaign folders; nothing else is written
    "sweep": re.compile(r"(?!)"),  # campaigns/value_NN likewise
}

#: an atomic write's temporary of NAME: ".NAME.XXXXXXXX..." (io_utils.atomic_write)
_TEMPORARY = re.compile(r"\.(.+)\.[A-Za-z0-9_]{8}.*")


def named_like_ours(kind: str, rel: str) -> bool:
    """Whether a path below a ``kind`` folder (relative, with '/') is named like a file genesis-rl writes there."""
    if kind in _FILE_PATTERNS:
        return rel in (MARKER, manifest.MANIFEST) or bool(_FILE_PATTERNS[kind].fullmatch(rel))
    top, _, rest = rel.partition("/")
    if not _own(kind, top):
        return False
    if not rest or (kind, top) not in OWN_FILES:
        return True
    pattern = re.compile(OWN_FILES[kind, top])
    temporary = _TEMPORARY.fullmatch(rest.rpartition("/")[2])
    head = rest.rpartition("/")[0]
    return bool(pattern.fullmatch(rest) or (temporary and pattern.fullmatch(
        (head + "/" if head else "") + temporary.group(1))))


def _named_like_ours_nested(folder: Path, kind: str, rel: str, kinds: dict[Path, str | None]) -> bool:
    """Whether ``rel``, below one of a ``kind`` folder's own folders, is named like a file genesis-rl writes there:
    judged by the deepest genesis-rl folder (one with a marker) around it, else by :data:`NESTED_OWN_FILES`.
    ``kinds`` keeps each folder's kind for the walk, so a marker is read once, not once per file below it."""
    parts = rel.split("/")
    for depth in range(len(parts) - 1, 0, -1):
        sub = Path(folder).joinpath(*parts[:depth])
        if sub not in kinds:
            kinds[sub] = folder_kind(sub) if (sub / MARKER).is_file() else None
        nested = kinds[sub]
        if nested is not None:
            return named_like_ours(nested, "/".join(parts[depth:]))
    return bool(NESTED_OWN_FILES[kind].fullmatch(rel))


def _own(kind: str, name: str) -> bool:
    """Whether a top-level entry of a ``kind`` folder is one genesis-rl writes (or a temporary of one)."""
    patterns = OWN_ENTRIES.get(kind, ())
    temporary = _TEMPORARY.fullmatch(name)
    return any(re.fullmatch(p, name) or (temporary and re.fullmatch(p, temporary.group(1))) for p in patterns)


def foreign_entries(folder: Path, kind: str) -> list[str]:
    """What ``--force`` may not delete in a run, campaign, export, ... folder, sorted: top-level entries
    genesis-rl does not write (folders end in '/'), files below its own folders named unlike its files, and,
    where the folder has a manifest, files named like its own that the manifest does not list with the same
    SHA-256 (a user's edit, or a user's file under one of our names). Empty for drive and render."""
    if kind not in OWN_ENTRIES:
        return []
    folder = Path(folder)
    listing = manifest.read(folder)
    died = _writer_died(folder)
    out = [p.name + ("/" if p.is_dir() and not p.is_symlink() else "") for p in folder.iterdir()
           if not _own(kind, p.name)]
    if listing is None and _promises_manifest(folder):
        return sorted([*out, f"{manifest.MANIFEST} ({_no_manifest(folder, died)})"])
    nested_kinds: dict[Path, str | None] = {}
    for rel, st in manifest.walk(folder):
        if not _own(kind, rel.partition("/")[0]):
            continue  # named above as a whole
        if not named_like_ours(kind, rel):
            out.append(rel)
        elif listing is None and kind in NESTED_OWN_FILES and "/" in rel \
                and not _named_like_ours_nested(folder, kind, rel, nested_kinds):
            out.append(rel)  # named by names alone: a file of a folder nested in ours must be named like its own
        elif listing is not None:
            why = _unlisted(listing, folder, rel, st, died)
            if why:
                out.append(f"{rel} ({why})")
    return sorted(out)


def _promises_manifest(folder: Path) -> bool:
    """Whether the folder's marker was written by a genesis-rl that keeps manifests (0.30.0 and older did not)."""
    return _json_object(Path(folder) / MARKER).get("manifest") is True


def _no_manifest(folder: Path, died: bool) -> str:
    if died:
        return (f"the run writing it was killed before it could list what it wrote (its lock "
                f"'{lock_path(folder).name}' is left): --resume it, or delete the folder yourself")
    return "missing or unreadable, so genesis-rl cannot tell its files from yours: delete the folder yourself"


def _unlisted(listing: manifest.Manifest, folder: Path, rel: str, st: os.stat_result, died: bool) -> str | None:
    """Why a file named like ours is not ours by the manifest; None when it is. A file a killed run wrote after
    the manifest's last record cannot be told from a user's edit since, so it is named too."""
    if manifest.is_listed(listing, folder, rel, st):
        return None
    if rel in listing.files:
        why = "changed since genesis-rl wrote it"
    else:
        why = "not in the folder's manifest of what genesis-rl wrote"
    if died:
        why += f"; the run writing the folder was killed (its lock '{lock_path(folder).name}' is left): --resume it"
    return why


#: the files that drive and render write: a marker-less folder holding only these is one of theirs (0.4.0)
_FILE_PATTERNS = {
    "drive": re.compile(r"summary\.json|telemetry(_scene_\d{4})?\.parquet|drive(_scene_\d{4})?\.gif"),
    "render": re.compile(r"rgb\.png|depth\.png|boxes\.png|boxes\.json|contact_sheet_\w+\.png"),
}


def _json_object(path: Path) -> dict:
    try:
        data = read_json(path, "marker")
    except (OSError, ValueError):  # a UserInputError (too big, too deep, not JSON) is a ValueError too
        return {}
    return data if isinstance(data, dict) else {}


def legacy_kind(folder: Path) -> str | None:
    """The kind of a genesis-rl 0.4.0 output folder (no marker), told by files only this package writes."""
    if _json_object(folder / "campaign.json").get("schema") == "genesis-rl/campaign":
        return "campaign"
    if (folder / "config.toml").is_file() and (
            _json_object(folder / "run.json").get("package") == "genesis-rl"
            or (folder / "checkpoints" / "last.json").is_file() or (folder / "agent.zip").is_file()):
        return "run"
    if (folder / "export.json").is_file() and (folder / "metadata.jsonl").is_file():
        return "export"
    names = [p.name for p in folder.iterdir()]
    for kind, pattern in _FILE_PATTERNS.items():
        if names and all(pattern.fullmatch(n) for n in names):
            return kind
    return None


def folder_kind(folder: Path) -> str | None:
    """The kind of output a folder holds: its marker's, else what its 0.4.0 content shows, else None."""
    marker = _json_object(folder / MARKER)
    if marker.get("schema") == MARKER_SCHEMA and marker.get("kind") in KINDS:
        return str(marker["kind"])
    return legacy_kind(folder)


def note_written(path: Path) -> None:
    """List a file the tool has just written beside a genesis-rl folder's own files (``report`` writing
    CAMPAIGN/report.html) in that folder's manifest, when its name is one the folder's kind writes."""
    folder = Path(path).parent
    kind = folder_kind(folder) if (folder / MARKER).is_file() else None
    if kind is not None and named_like_ours(kind, Path(path).name):
        try:
            manifest.note(folder, Path(path).name)
        except OSError:
            pass  # unlisted, it is then named by --force rather than deleted


def check_overwrite(path: Path) -> None:
    """Refuse ``--force`` onto a file beside a genesis-rl folder's own (``report`` onto CAMPAIGN/report.html)
    that its manifest does not list as written by the tool: a user's edit of it, or a user's file of that name."""
    path = Path(path)
    folder = path.parent
    kind = folder_kind(folder) if (folder / MARKER).is_file() else None
    if kind is None or not named_like_ours(kind, path.name):
        return
    listing = manifest.read(folder)
    if listing is None:
        return  # a folder of 0.30.0: judged by the name, as before
    why = _unlisted(listing, folder, path.name, os.lstat(path), _writer_died(folder))
    if why:
        raise UserInputError(f"--force: '{path}' ({why}); refusing to overwrite it; move it away, or choose another "
                             "--out")


def lock_path(folder: Path) -> Path:
    folder = Path(folder).resolve()
    return folder.parent / f".{folder.name}.genesis-rl.lock"


@dataclass
class _Hold:
    fd: int
    depth: int
    started_ns: int  # files named like ours modified since are this process's writes
    died: bool  # the lock file was there, unlocked: the last writer was killed before it let the folder go


_HELD: dict[Path, _Hold] = {}  # lock path -> its hold: re-entrant within one process


def _writer_died(folder: Path) -> bool:
    """Whether the last process that held the folder was killed holding it: its lock file is still there and
    nobody holds it (the kernel dropped the lock; the file stays)."""
    path = lock_path(folder)
    if path in _HELD:
        return _HELD[path].died
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return True
    except OSError:
        return False  # held by a live writer
    finally:
        os.close(fd)
