"""The SHA-256 of a file: the one digest that pins runs, campaigns, weights and models."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path


def file_sha256(path: str | Path) -> str:
    """The file's SHA-256, read in 1 MiB chunks (weights files are tens of MB)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def regular_file_sha256(path: str | Path) -> str | None:
    """:func:`file_sha256` of a regular file; None when it is missing or is not one (a FIFO is never opened)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        return file_sha256(path)
    except OSError:
        return None
