"""Links and special files as outputs: a rename onto one would replace a link, a FIFO or a device with a regular
file, so every write checks here first (``io_utils`` for each atomic write, ``output_paths`` for each command's
output). Its own module so that both can import it without importing each other."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from genesis_rl.core.errors import UserInputError

#: the one device written in place
DISCARD = "/dev/null"


def special_kind(path: Path) -> str | None:
    """What a path is when it is not a plain file or folder (by ``lstat``: a link is a link), else None."""
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    for test, name in ((stat.S_ISLNK, "symbolic link"), (stat.S_ISFIFO, "FIFO (named pipe)"),
                       (stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"),
                       (stat.S_ISSOCK, "socket")):
        if test(mode):
            return name
    return "special file"


def refuse_special(path: Path, what: str = "output") -> None:
    """Refuse a path that is a symbolic link or a special file: writing a file there by rename would replace
    it (a link, a device, a pipe) with a regular file."""
    kind = special_kind(Path(path))
    if kind is None:
        return
    if kind == "symbolic link":
        raise UserInputError(f"{what} '{path}' is a symbolic link to '{os.readlink(path)}'; genesis-rl neither "
                             "replaces a link nor writes through one: pass the target itself, or remove the link")
    raise UserInputError(f"{what} '{path}' is a {kind}, not a regular file; refusing to replace it; write to a "
                         f"regular file, a FIFO, {DISCARD} or '-' (standard output)")
