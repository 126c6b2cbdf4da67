"""Output folders that ``--force`` may replace, and that one command at a time writes.

A folder this package creates gets a marker file, ``.genesis-rl.json``, naming the kind of output (run,
campaign, export, drive, render) and the package version. ``--force`` replaces (or, for drive and render,
overwrites the outputs in) only a folder whose marker names the same kind, and in it only the files its
manifest (``manifest.py``) lists with the same SHA-256; anything else is refused, naming the folder and what is
in it, so a mistyped ``--out`` or a hand-edited summary cannot cost a user's work. Folders written by
genesis-rl 0.4.0 carry no marker and are recognised by their content instead (``legacy_kind``). An output
folder is never the input of the same command, nor contains it.

While a command writes a folder it holds an exclusive OS lock (``flock``) on a lock file beside it,
``.NAME.genesis-rl.lock``; a second writer is refused at once, naming the holder's pid. The kernel drops the
lock when its process dies, so a killed run's lock is taken over without any clean-up.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import time
from collections.abc import Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from genesis_rl import __version__
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import manifest, output_paths
from genesis_rl.core.files.io_utils import (
    atomic_write_json,
    ensure_folder_path,
    os_error_message,
    remove_tree,
)
from genesis_rl.core.parsing import read_json
from genesis_rl.core.signals import deferred_signals

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
    for rel, st in manifest.walk(folder):
        if not _own(kind, rel.partition("/")[0]):
            continue  # named above as a whole
        if not named_like_ours(kind, rel):
            out.append(rel)
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
        from genesis_rl.core.parsing import read_json

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


def _entries(folder: Path, shown: int = 4) -> str:
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in folder.iterdir())
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return ", ".join(names[:shown]) + more


def check_folder_inputs(folder: Path, inputs: Sequence[str | Path | None], nested_ok: bool = False,
                 files: Sequence[str] | None = None) -> None:
    """Refuse an output folder that is an input of the same command, holds one, or (unless ``nested_ok``:
    ``evaluate`` writes RUN/eval by default) lies inside one. With ``files`` (drive, render: the folder gets
    these files added) only an input that is the folder or one of those files is refused. The one rule of
    every output (``output_paths``): paths are compared with their links resolved."""
    output_paths.check_folder_output(folder)
    output_paths.check_inputs(folder, inputs, folder=True, nested_ok=nested_ok, files=files)


def check_target(folder: Path, kind: str, force: bool, files: Sequence[str] | None = None,
                 resume_hint: bool = False) -> None:
    """Refuse, before anything is written, an output folder that the command may not write: an existing
    one without ``--force`` (for drive and render: one holding a file of the same name), or, with
    ``--force``, one that is not a genesis-rl folder of this kind."""
    folder = Path(folder)
    ensure_folder_path(folder)
    if not folder.is_dir() or not any(folder.iterdir()):
        return
    clashes = [n for n in files if (folder / n).exists()] if files is not None else None
    if clashes == []:
        return  # drive and render add files beside others; nothing is overwritten
    if not force:
        if clashes:
            raise UserInputError(f"output '{folder / clashes[0]}' already exists; pass --force to overwrite it")
        hint = "--resume to continue it or --force to replace it" if resume_hint else "--force to replace it"
        label = f"{kind} folder" if kind in ("run", "campaign", "benchmark", "sweep") else "output"
        raise UserInputError(f"{label} '{folder}' exists; pass {hint}")
    found = folder_kind(folder)
    if found == kind and clashes:
        listing = manifest.read(folder)
        changed = [f"{n} ({why})" for n in clashes if listing is not None
                   and (why := _unlisted(listing, folder, n, os.lstat(folder / n), _writer_died(folder)))]
        if changed:
            raise UserInputError(f"--force: '{folder}' holds {', '.join(changed)}; refusing to overwrite it; move it "
                                 "out of the folder, or choose another --out")
        return
    if found == kind:
        foreign = foreign_entries(folder, kind)
        if foreign:
            shown = ", ".join(foreign[:6]) + (f" and {len(foreign) - 6} more" if len(foreign) > 6 else "")
            raise UserInputError(f"--force: {kind} folder '{folder}' also holds what genesis-rl did not write there: "
                                 f"{shown}; refusing to delete it; move it out of the folder, or choose another "
                                 "--out")
        return
    why = (f"it holds a genesis-rl {found} output" if found else f"no {MARKER}") + f": {_entries(folder)}"
    action = "delete it" if kind in WHOLE_FOLDER else "overwrite files in it"
    hint = " (is it a training run? campaigns go to RUN/eval)" if (kind, found) == ("campaign", "run") else ""
    raise UserInputError(f"--force: '{folder}' is not a {kind} folder written by genesis-rl ({why}); refusing to "
                         f"{action}{hint}; choose another --out, or empty it yourself")


def write_marker(folder: Path, kind: str) -> None:
    """Mark the folder as this kind's; ``manifest: true`` says that it keeps a manifest (``manifest.py``), so that
    a missing one is damage, not a folder of 0.30.0."""
    atomic_write_json(Path(folder) / MARKER, {"schema": MARKER_SCHEMA, "kind": kind, "version": __version__,
                                              "manifest": True}, indent=2)


def recorded_spec(path: Path, kind: str) -> dict[str, Any]:
    """The spec a resumable folder's result file (``benchmark.json``, ``harden.json``, ...) was started with."""
    path = Path(path)
    if not path.exists():
        raise UserInputError(f"--resume: '{path.parent}' holds no {path.name}; start it without --resume")
    data = read_json(path, f"{kind} '{path.parent}': {path.name}")
    found = data.get("spec") if isinstance(data, dict) else None
    if not isinstance(found, dict):
        raise UserInputError(f"--resume: '{path}' holds no {kind} spec; start the {kind} again with --force")
    return found


def check_same_settings(kind: str, folder: Path, found: Mapping[str, Any], wanted: Mapping[str, Any], *,
                        may_change: Collection[str] = (), defaults: Mapping[str, Any] | None = None) -> None:
    """Refuse a ``--resume`` whose settings differ from those ``folder`` was started with, naming the first that
    does. ``may_change``: settings a resume may change; ``defaults``: what a setting added since the folder was
    started meant when its spec lacks it."""
    defaults = defaults or {}
    for key, value in wanted.items():
        before = found.get(key, defaults.get(key))
        if key not in may_change and before != value:
            raise UserInputError(f"--resume: {kind} '{folder}' was started with {key} = {before!r}, not {value!r}; "
                                 "resume it with the same settings, or start again with --force")


def replace(folder: Path, kind: str) -> None:
    """Empty (or create) the folder and mark it as this kind's. Call it under ``hold`` after ``check_target``.
    Of a run, campaign or export folder only genesis-rl's own entries are removed (``OWN_ENTRIES``)."""
    folder = Path(folder)
    if folder.is_dir():
        for entry in folder.iterdir():
            if kind in OWN_ENTRIES and not _own(kind, entry.name):
                continue  # check_target refused such a folder; one that appeared since is kept
            if entry.is_dir() and not entry.is_symlink():
                remove_tree(entry)
            else:
                entry.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    write_marker(folder, kind)


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


def _acquire(path: Path, folder: Path) -> int:
    while True:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise _lock_error(folder, path, err) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            holder = os.read(fd, 32).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise UserInputError(f"output folder '{folder}' is being written by another genesis-rl process "
                                     f"(pid {holder}); wait for it to finish or choose another --out") from None
            raise _lock_error(folder, path, err) from None
        try:  # the holder before us may have removed the file as it released it: lock the file now there
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            try:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            except OSError as err:  # a full disk: release and remove the lock, leave nothing behind
                path.unlink(missing_ok=True)
                os.close(fd)
                raise _lock_error(folder, path, err) from None
            return fd
        os.close(fd)


def _lock_error(folder: Path, path: Path, err: OSError) -> UserInputError:
    cause = os_error_message(OSError(err.errno, err.strerror, str(path))) or f"{err.strerror} ({path})"
    return UserInputError(f"cannot lock output folder '{folder}': {cause}")


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


def _record_manifest(folder: Path, hold: _Hold) -> None:
    """List what this process wrote into the folder, as it lets it go (``manifest.record``). A folder without a
    manifest by now (new, replaced by --force, or of genesis-rl 0.30.0) adopts every file named like ours."""
    folder = Path(folder)
    kind = folder_kind(folder) if folder.is_dir() else None
    if kind is None or not (folder / MARKER).is_file():
        return  # a folder drive or render added files to stays unmarked, and unlisted
    listing = manifest.read(folder)
    since = 0 if listing is None else listing.recorded_ns if hold.died else hold.started_ns
    # a folder marked during this hold (new, or replaced by --force) gets its manifest even if nothing else was
    # written yet: its marker promises one
    marked_now = (folder / MARKER).stat().st_mtime_ns >= hold.started_ns
    try:
        manifest.record(folder, lambda rel: named_like_ours(kind, rel), since,
                        0 if marked_now and listing is None else hold.started_ns)
    except OSError:
        pass  # a full disk: --force then judges the newest files by the manifest they are missing from


@contextmanager
def hold(folder: Path) -> Iterator[None]:
    """Hold the folder exclusively (re-entrant within this process) for the block; as the outermost hold ends,
    record what was written (``manifest``)."""
    path = lock_path(folder)
    if path in _HELD:
        _HELD[path].depth += 1
    else:
        started = time.time_ns()
        stale = path.exists()
        fd = _acquire(path, Path(folder))
        _HELD[path] = _Hold(fd, 1, started, stale)
    try:
        yield
    finally:
        _HELD[path].depth -= 1
        if _HELD[path].depth == 0:
            held = _HELD[path]
            try:
                with deferred_signals():
                    _record_manifest(folder, held)
            finally:
                _HELD.pop(path)
                try:
                    path.unlink(missing_ok=True)  # while still locked, so no one locks a file that is going away
                except OSError:
                    pass
                os.close(held.fd)


@contextmanager
def claim(folder: Path, kind: str, force: bool, *, resume: bool = False, files: Sequence[str] | None = None,
          inputs: Sequence[str | Path | None] = (), nested_ok: bool = False) -> Iterator[bool]:
    """Check the folder (inputs, content, ``--force``), then hold it for the block, checking again under the
    lock: a writer that finished meanwhile may have filled it. Yields whether the folder was new or empty:
    drive and render then mark it as theirs (``write_marker``) once they have written; a folder that already
    held other files stays unmarked, so ``--force`` will not overwrite files in it. ``resume`` skips the
    content check (the command checks what it resumes) and marks a 0.4.0 folder it continues."""
    if kind not in KINDS:
        raise ValueError(f"unknown output kind {kind!r}")
    check_folder_inputs(folder, inputs, nested_ok, files)
    if resume:
        ensure_folder_path(Path(folder))
    else:
        check_target(folder, kind, force, files, resume_hint=kind in RESUMABLE)
    with hold(folder):
        if not resume:
            check_target(folder, kind, force, files, resume_hint=kind in RESUMABLE)
        elif Path(folder).is_dir() and not (Path(folder) / MARKER).exists() and legacy_kind(Path(folder)) == kind:
            write_marker(folder, kind)
        yield not Path(folder).is_dir() or not any(Path(folder).iterdir())
