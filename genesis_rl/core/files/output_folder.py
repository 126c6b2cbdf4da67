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
import time
from collections.abc import Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager
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
from genesis_rl.core.files.ownership import (  # noqa: F401 - the folder rules' names, as they were found here
    _HELD,
    KINDS,
    MARKER,
    MARKER_SCHEMA,
    OWN_ENTRIES,
    OWN_FILES,
    RESUMABLE,
    WHOLE_FOLDER,
    _Hold,
    _own,
    _unlisted,
    _writer_died,
    check_overwrite,
    folder_kind,
    foreign_entries,
    legacy_kind,
    lock_path,
    named_like_ours,
    note_written,
)
from genesis_rl.core.parsing import read_json
from genesis_rl.core.signals import deferred_signals


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
