"""What genesis-rl wrote into an output folder, file by file, with each file's SHA-256.

``--force`` may delete only what the tool wrote. Names alone cannot tell: a user's ``summary.json`` edited by
hand, or a note saved as ``records/agent_scene_0001.json``, looks like ours. So every output folder keeps a
manifest, ``.genesis-rl.manifest.json``, written when the command that held the folder lets it go: every file
named like the tool's that the command wrote, with its size, modification time and SHA-256. ``--force`` then
deletes a file only when the manifest lists it with the same digest; anything else is named and the command
refused.

A folder written by genesis-rl 0.30.0 or older has no manifest and is judged by names, as before manifests
existed (its files named like ours are adopted the next time a command writes into it); its marker says so
(no ``"manifest": true``). A folder whose marker promises a manifest that is missing or unreadable, or a run
killed before it could list what it wrote, cannot be told apart from a user's edits: ``--force`` refuses it and
says why.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from genesis_rl.core.files.hashing import file_sha256

MANIFEST = ".genesis-rl.manifest.json"
MANIFEST_SCHEMA = "genesis-rl/manifest"
#: a manifest is the tool's own bookkeeping; its own size is bounded by what a folder can hold
MANIFEST_MAX_BYTES = 256 * 1024 * 1024


@dataclass(frozen=True)
class Entry:
    """One file the tool wrote: what identifies its content (``sha256``) and what tells cheaply that it is
    unchanged since (``size``, ``mtime_ns``)."""

    sha256: str
    size: int
    mtime_ns: int


@dataclass(frozen=True)
class Manifest:
    files: dict[str, Entry]
    recorded_ns: int  # when it was written: files named like ours modified after it may be a killed run's


def read(folder: Path) -> Manifest | None:
    """The folder's manifest; None when it has none (a folder of 0.30.0 or older) or it cannot be read (then
    the folder is judged by names, as one without)."""
    path = Path(folder) / MANIFEST
    try:
        if path.is_symlink() or not path.is_file() or path.stat().st_size > MANIFEST_MAX_BYTES:
            return None
        data = json.loads(path.read_text(encoding="utf-8"))
        files = {str(rel): Entry(str(e["sha256"]), int(e["size"]), int(e["mtime_ns"]))
                 for rel, e in data["files"].items()}
        if data.get("schema") != MANIFEST_SCHEMA:
            return None
        return Manifest(files, int(data["recorded_ns"]))
    except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError):
        return None


def _write(folder: Path, manifest: Manifest) -> None:
    from genesis_rl.core.files.io_utils import atomic_write_json

    atomic_write_json(Path(folder) / MANIFEST, {
        "schema": MANIFEST_SCHEMA, "recorded_ns": manifest.recorded_ns,
        "files": {rel: {"sha256": e.sha256, "size": e.size, "mtime_ns": e.mtime_ns}
                  for rel, e in sorted(manifest.files.items())}})


def walk(folder: Path) -> Iterator[tuple[str, os.stat_result]]:
    """Every file and link below ``folder`` as (path relative to it with '/', its lstat), the manifest and the
    marker at the top left out. Links are listed, never followed."""
    folder = Path(folder)
    for dirpath, dirnames, filenames in os.walk(folder):
        links = [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]
        for name in filenames + links:
            full = os.path.join(dirpath, name)
            rel = os.path.relpath(full, folder).replace(os.sep, "/")
            if rel in (MANIFEST, ".genesis-rl.json"):
                continue
            try:
                yield rel, os.lstat(full)
            except OSError:
                continue  # gone meanwhile


def _unchanged(entry: Entry, st: os.stat_result) -> bool:
    return entry.size == st.st_size and entry.mtime_ns == st.st_mtime_ns


def record(folder: Path, named_like_ours: Callable[[str], bool], since_ns: int, held_ns: int) -> None:
    """Write the folder's manifest as a command lets it go: the files it listed that are unchanged, and every
    regular file named like ours modified at or after ``since_ns`` (the command's own writes; 0 adopts every
    such file), each hashed once. A listed file changed before ``since_ns`` was changed by someone else and
    leaves the manifest. A command that wrote nothing named like ours since it took the folder (``held_ns``:
    one refused under the lock) leaves the folder as it was, manifest included; ``held_ns`` 0 always writes (a
    folder marked in this hold)."""
    import stat

    folder = Path(folder)
    if not folder.is_dir():
        return
    old = read(folder)
    before = old.files if old else {}
    now = time.time_ns()
    files: dict[str, Entry] = {}
    wrote = False
    for rel, st in walk(folder):
        if not stat.S_ISREG(st.st_mode) or not named_like_ours(rel):
            continue
        wrote = wrote or st.st_mtime_ns >= held_ns
        known = before.get(rel)
        if known is not None and _unchanged(known, st):
            files[rel] = known
        elif st.st_mtime_ns >= since_ns:
            try:
                files[rel] = Entry(file_sha256(folder / rel), st.st_size, st.st_mtime_ns)
            except OSError:
                continue
    if wrote or held_ns == 0:  # a refused command leaves even the manifest as it was: a listed file it found
        _write(folder, Manifest(files, now))  # edited stays listed with the bytes genesis-rl wrote, so it is not ours


def note(folder: Path, rel: str) -> None:
    """Add one file the tool has just written into a folder it does not hold (``report`` writing report.html
    into a campaign) to that folder's manifest, if it has one."""
    folder = Path(folder)
    old = read(folder)
    if old is None:
        return
    try:
        st = os.stat(folder / rel)
        entry = Entry(file_sha256(folder / rel), st.st_size, st.st_mtime_ns)
    except OSError:
        return
    _write(folder, Manifest({**old.files, rel: entry}, old.recorded_ns))


def is_listed(manifest: Manifest, folder: Path, rel: str, st: os.stat_result) -> bool:
    """Whether the file at ``rel`` is, to the byte, one the manifest lists."""
    entry = manifest.files.get(rel)
    if entry is None or entry.size != st.st_size:
        return False
    try:
        return file_sha256(Path(folder) / rel) == entry.sha256
    except OSError:
        return False
