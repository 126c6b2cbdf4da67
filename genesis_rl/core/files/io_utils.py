"""Atomic, non-clobbering writes: results are never half-written and never overwritten without --force."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.special_files import refuse_special
from genesis_rl.core.signals import deferred_signals

if TYPE_CHECKING:
    pass


def ensure_writable(path: Path, force: bool) -> None:
    """Refuse to overwrite an existing output unless ``force`` is set, and refuse outright a path that
    ``--force`` could not help: a folder where a file goes, or a file where a folder goes."""
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"output '{path}' is a directory; expected a file path")
    ensure_folder_path(path.parent, flag="output folder")
    if (path.exists() or path.is_symlink()) and not force:  # a dangling link is the user's too
        raise UserInputError(f"output '{path}' already exists; pass --force to overwrite it")
    refuse_special(path)  # --force replaces a file, never a link, a device or a pipe (special_files)


def ensure_folder_path(path: Path, flag: str = "--out") -> None:
    """An output folder may not be, or lie inside, an existing file (which --force would not help with)."""
    path = Path(path)
    for candidate in (path, *path.parents):
        if candidate.exists():
            if not candidate.is_dir():
                raise UserInputError(f"{flag} '{path}': '{candidate}' is a file; expected a folder")
            return


@deferred_signals()  # Ctrl-C or SIGTERM waits for the rename: no temporary left, no torch error (signals.py)
def atomic_write(path: Path, writer: Callable[[Path], object]) -> None:
    """Call ``writer(tmp_path)`` then rename the temporary file onto ``path`` (atomic on POSIX). A failure
    leaves no temporary file behind; one that the machine caused (permission, read-only, disk full, ...)
    is raised as an ``OSError`` naming ``path``, whatever library the writer used (pyarrow, torch, PIL)."""
    path = Path(path)
    refuse_special(path)  # a rename would replace a link, a FIFO or a device with a regular file
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix or ".tmp", dir=path.parent)
    except OSError as err:  # mkstemp names its random file; the user knows the output's name
        raise _naming(err, path) or err from None
    os.close(fd)
    try:
        writer(Path(tmp))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give results the usual permissions
        refuse_special(path)  # again: one may have been put there while the writer ran
        os.replace(tmp, path)
    except Exception as err:
        Path(tmp).unlink(missing_ok=True)
        named = _naming(err, path)
        if named is None:
            raise
        raise named from err
    except BaseException:  # KeyboardInterrupt: clean up, and let it through as it is
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_tree(path: Path) -> None:
    """``shutil.rmtree``, its error naming the full path of the entry it could not remove (rmtree's own error
    names it relative to the folder it was in)."""
    def named(func: Any, entry: str, exc_info: Any) -> None:
        err = exc_info[1]
        if isinstance(err, OSError) and err.errno is not None:
            raise OSError(err.errno, err.strerror, entry) from err
        raise err

    shutil.rmtree(path, onerror=named)  # onexc from Python 3.12; onerror works on 3.10 to 3.13


def _naming(err: BaseException, path: Path) -> OSError | None:
    """``err`` as an OSError naming ``path``, when the machine caused it: an OSError with an errno (or, as
    pyarrow words it, "[errno N]" in its message), or any error of a writer on a disk now full (torch
    reports a failed write as a RuntimeError)."""
    code = err.errno if isinstance(err, OSError) else None
    if code is None:
        found = re.search(r"\[errno (\d+)\]", str(err), re.IGNORECASE)
        code = int(found.group(1)) if found else None
    if code is None and _disk_full(path.parent):
        code = errno.ENOSPC
    if code is None:
        return None
    return OSError(code, os.strerror(code), str(path))


def _disk_full(folder: Path) -> bool:
    try:
        return os.statvfs(folder).f_bavail == 0
    except OSError:
        return False


#: errors the machine or the file system causes (not bugs), with what the user can do about each
OS_ERROR_HINTS: dict[int, str] = {
    errno.EACCES: "check the folder's permissions or choose another output path",
    errno.EPERM: "check the file's permissions and attributes (lsattr) or choose another output path",
    errno.EROFS: "choose an output path on a writable file system",
    errno.ENOSPC: "free some space and run again (train and evaluate continue with --resume)",
    errno.EDQUOT: "free some space and run again (train and evaluate continue with --resume)",
    errno.EFBIG: "choose an output path on a file system that allows larger files",
    errno.ENAMETOOLONG: "shorten the path (most file systems allow 255 bytes a name)",
    errno.ENOTDIR: "a part of the path is a file where a folder should be",
    errno.EISDIR: "a folder is where a file should be",
    errno.ENOENT: "check the path",
    errno.EEXIST: "remove it or choose another path",
    errno.ENOTEMPTY: "remove it or choose another path",
    errno.ELOOP: "check the symbolic links on the path",
    errno.EIO: "the disk or network file system failed; check it and run again",
    errno.EMFILE: "raise the limit of open files (ulimit -n)",
    errno.ENFILE: "close other programs or raise the system's limit of open files",
    errno.EXDEV: "keep the input and output on one file system",
    errno.ETXTBSY: "wait for the program using it to finish",
    errno.EPIPE: "the program reading the output (a pipe) ended before it was written",
}


def os_error_message(err: OSError, hint: bool = True) -> str | None:
    """One line for an OSError the machine caused, naming the path and the cause (and, with ``hint``, what to
    do about it); None for any other."""
    if err.errno not in OS_ERROR_HINTS:
        return None
    paths = [p for p in (err.filename, err.filename2) if p is not None]
    where = " -> ".join(f"'{os.fsdecode(p)}'" for p in paths) if paths else "a file"
    cause = err.strerror or os.strerror(err.errno)
    return f"{where}: {cause} ({errno.errorcode[err.errno]})" + (f"; {OS_ERROR_HINTS[err.errno]}" if hint else "")


def atomic_write_text(path: Path, text: str) -> None:
    """UTF-8; a file name that is not UTF-8 (a surrogate in ``text``) is written as its escape, ``\\udcff``."""
    atomic_write(path, lambda p: p.write_text(text, encoding="utf-8", errors="backslashreplace"))


def atomic_write_json(path: Path, data: Any, indent: int | None = None) -> None:
    atomic_write_text(path, json.dumps(data, indent=indent, separators=None if indent else (",", ":")))


def read_utf8(path: Path, what: str = "file") -> str:
    """A text file's content; bytes that are not UTF-8 are a user error that names the file."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise UserInputError(f"{what} '{path}' is not UTF-8 text ({err.reason} at byte {err.start})") from None

