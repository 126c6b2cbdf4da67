"""Atomic, non-clobbering writes: results are never half-written and never overwritten without --force."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from genesis_rl.errors import UserInputError


def ensure_writable(path: Path, force: bool) -> None:
    """Refuse to overwrite an existing output unless ``force`` is set, and refuse outright a path that
    ``--force`` could not help: a folder where a file goes, or a file where a folder goes."""
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"output '{path}' is a directory; expected a file path")
    ensure_folder_path(path.parent, flag="output folder")
    if path.exists() and not force:
        raise UserInputError(f"output '{path}' already exists; pass --force to overwrite it")


def ensure_folder_path(path: Path, flag: str = "--out") -> None:
    """An output folder may not be, or lie inside, an existing file (which --force would not help with)."""
    path = Path(path)
    for candidate in (path, *path.parents):
        if candidate.exists():
            if not candidate.is_dir():
                raise UserInputError(f"{flag} '{path}': '{candidate}' is a file; expected a folder")
            return


def atomic_write(path: Path, writer: Callable[[Path], None]) -> None:
    """Call ``writer(tmp_path)`` then rename the temporary file onto ``path`` (atomic on POSIX)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix or ".tmp", dir=path.parent)
    os.close(fd)
    try:
        writer(Path(tmp))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give results the usual permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def atomic_write_json(path: Path, data: Any, indent: int | None = None) -> None:
    atomic_write_text(path, json.dumps(data, indent=indent, separators=None if indent else (",", ":")))


def read_utf8(path: Path, what: str = "file") -> str:
    """A text file's content; bytes that are not UTF-8 are a user error that names the file."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise UserInputError(f"{what} '{path}' is not UTF-8 text ({err.reason} at byte {err.start})") from None


def read_json(path: Path, what: str = "file") -> Any:
    """A JSON file's content; a damaged file is a user error that names it, not a traceback."""
    text = read_utf8(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise UserInputError(f"{what} '{path}' is not valid JSON: {err}") from None
