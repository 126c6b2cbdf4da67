"""Pins of what a resumable folder keeps: ``pins.json`` records, for each file or folder that ``--resume``
reuses instead of recomputing (a stage's campaign, a kept round, a checkpoint, cached data, a trained agent),
the sha256 of every file in it as genesis-rl wrote it, and for a stage that a resume may legitimately replace,
the spec it was started with.

A resume checks an entry before it reuses it: a file that changed, went missing or was added is refused with
one line naming it (start again with ``--force``). An entry whose file or folder is gone altogether is not an
error: it is computed again, as deleting a stage always meant. An entry that is not pinned (a folder written
before the pins, or a write that a killed process did not get to pin) is trusted as it is and pinned from then
on. A file that genesis-rl rewrites in place (an estimate's ``episodes.csv`` after every batch) is written
through :meth:`Pins.write_bytes`, which pins the new digest beside the old one before the rename and drops the
old one after it, so that a process killed between the two leaves a pin that still matches.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.hashing import regular_file_sha256
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json
from genesis_rl.core.parsing import read_json

NAME = "pins.json"
SCHEMA = "genesis-rl/pins"
#: which files of a folder an entry pins (a path relative to the folder); None: every file
Include = Callable[[str], bool] | None
_NO_SPEC = object()


def plain(value: Any) -> Any:
    """``value`` as JSON reads it back (tuples become lists), so that a pinned spec compares with a new one."""
    return json.loads(json.dumps(value, default=str))


def _digest(path: Path) -> str:
    """A file's sha256; a link to a FIFO or device is never opened (it can match no pin)."""
    return regular_file_sha256(path) or "not a regular file"


def _files(root: Path, include: Include) -> dict[str, str]:
    """The sha256 of every file under ``root`` (of ``root`` itself, under the name ``""``, when it is not a
    folder); hidden entries (markers, locks, temporaries of atomic writes) are not part of what a folder holds."""
    if not root.is_dir():
        return {"": _digest(root)}
    out: dict[str, str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in sorted(filenames):
            if name.startswith("."):
                continue
            rel = Path(dirpath, name).relative_to(root).as_posix()
            if include is None or include(rel):
                out[rel] = _digest(Path(dirpath, name))
    return out


class Pins:
    """The ledger ``folder/pins.json``. Every call reads it afresh and writes it whole (a ledger is a few
    hundred kB at most), so that two holders in one process (the loop and a retrain hook) never lose an
    update."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.path = self.folder / NAME

    @classmethod
    def start(cls, folder: Path) -> Pins:
        """A new, empty ledger (a fresh run): a folder without one on ``--resume`` predates the pins."""
        pins = cls(folder)
        pins._save({})
        return pins

    # -- the ledger ---------------------------------------------------------------------------------------------
    def _entries(self) -> dict[str, dict[str, Any]]:
        if not self.path.is_file():
            return {}
        data = read_json(self.path, "pins file")
        entries = data.get("entries") if isinstance(data, dict) and data.get("schema") == SCHEMA else None
        ok = isinstance(entries, dict) and all(
            isinstance(e, dict) and isinstance(e.get("files", {}), dict)
            and all(isinstance(v, list) and v and all(isinstance(s, str) for s in v)
                    for v in e.get("files", {}).values())
            for e in entries.values())
        if not ok:
            raise UserInputError(f"--resume: '{self.path}' is damaged (expected {SCHEMA} entries of sha256 "
                                 "lists); start again with --force")
        return entries  # type: ignore[return-value]  # checked just above

    def _save(self, entries: dict[str, dict[str, Any]]) -> None:
        atomic_write_json(self.path, {"schema": SCHEMA, "entries": entries}, indent=1)

    def key(self, path: Path) -> str:
        """An entry's name: its path relative to the ledger's folder (a moved folder keeps its pins), else its
        absolute path (an input outside the folder)."""
        path, folder = Path(path).resolve(), self.folder.resolve()
        try:
            return path.relative_to(folder).as_posix()
        except ValueError:
            return str(path)

    # -- pinning ------------------------------------------------------------------------------------------------
    def record(self, path: Path, include: Include = None, spec: Any = _NO_SPEC) -> None:
        """Pin ``path`` (a file, or the files of a folder that ``include`` admits) as it is now; ``spec``: what
        it was made from (kept from an earlier :meth:`note_spec` when not given)."""
        entries = self._entries()
        key = self.key(path)
        entry: dict[str, Any] = {"files": {k: [v] for k, v in _files(Path(path), include).items()}}
        before = entries.get(key, {})
        if spec is not _NO_SPEC:
            entry["spec"] = plain(spec)
        elif "spec" in before:
            entry["spec"] = before["spec"]
        entries[key] = entry
        self._save(entries)

    def note_spec(self, path: Path, spec: Any) -> None:
        """Record what a stage about to run is made from (its files are pinned when it ends)."""
        entries = self._entries()
        entries[self.key(path)] = {"spec": plain(spec)}
        self._save(entries)

    def spec(self, path: Path) -> Any:
        """The spec pinned for ``path``; None when none is."""
        return self._entries().get(self.key(path), {}).get("spec")

    def forget(self, path: Path) -> None:
        """Drop the entry of a stage that is replaced (a resume that moved it to other settings)."""
        entries = self._entries()
        if entries.pop(self.key(path), None) is not None:
            self._save(entries)

    def write_bytes(self, path: Path, data: bytes) -> None:
        """Write ``data`` to ``path`` atomically, pinned: the new digest is accepted beside the old one until the
        rename has happened, so a process killed in between leaves a file its pin still matches."""
        entries = self._entries()
        key, sha = self.key(path), hashlib.sha256(data).hexdigest()
        found = regular_file_sha256(path)  # checked on resume, or written by us since
        now = [found] if found else []
        entries[key] = {"files": {"": [*now, sha]}}
        self._save(entries)
        atomic_write(Path(path), lambda p: p.write_bytes(data))
        entries[key] = {"files": {"": [sha]}}
        self._save(entries)

    # -- checking -----------------------------------------------------------------------------------------------
    def check(self, path: Path, include: Include = None) -> bool:
        """Whether ``path`` is pinned and holds what was pinned; raises naming the first file that does not.
        False when nothing is pinned for it (trust it, and :meth:`record` it) or when it is gone altogether
        (compute it again)."""
        path = Path(path)
        pinned = self._entries().get(self.key(path), {}).get("files")
        if not pinned or not path.exists():
            return False
        found = _files(path, include)
        for sub, accepted in sorted(pinned.items()):
            name = path / sub if sub else path
            if sub not in found:
                raise UserInputError(f"--resume: '{name}' is missing: it was there when genesis-rl wrote "
                                     f"'{path}' ({self.path} pins it); start again with --force")
            if found[sub] not in accepted:
                raise UserInputError(f"--resume: '{name}' changed since genesis-rl wrote it ({self.path} pins "
                                     f"sha256 {accepted[-1][:12]}, found {found[sub][:12]}): it was edited or "
                                     "belongs to another run; start again with --force")
        added = sorted(set(found) - set(pinned))
        if added:
            raise UserInputError(f"--resume: '{path / added[0]}' was not there when genesis-rl wrote '{path}' "
                                 f"({self.path} pins what it held): it was added or belongs to another run; "
                                 "start again with --force")
        return True

    def check_or_record(self, path: Path, include: Include = None) -> None:
        """:meth:`check` a kept ``path``, pinning it as it is when nothing was pinned (trusted on first use)."""
        if not self.check(path, include) and Path(path).exists():
            self.record(path, include)
