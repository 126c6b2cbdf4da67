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
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise UserInputError(f"output '{path}': '{parent}' is a file, not a directory")
            break
    if path.exists() and not force:
        raise UserInputError(f"output '{path}' already exists; pass --force to overwrite it")


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
