"""One rule for every output a command writes: never onto its own input, never a link or device replaced.

Every command checks each output before it starts any work:

* **Inputs.** The output and every input the command reads (files and folders: a catalog, a config, a campaign,
  a run) are resolved, symbolic links followed. The output is refused, naming both, when it *is* an input (the
  same path, or the same file by another name: a link, a hard link), when it *holds* one (a folder output), or
  when it *lies inside* an input folder. The one exception is a product the command itself puts into that
  folder by design, beside the files it reads and never onto them: ``report`` writes ``CAMPAIGN/report*.html``,
  ``reactivity`` ``CAMPAIGN/reactivity_*.json``, ``evaluate`` its campaign into ``RUN/eval``. So
  ``report CAMP --out CAMP/campaign.json --force`` and ``compare ... --json CAMP/campaign.json --force`` are
  refused, while ``report CAMP`` (``CAMP/report.html``) is not.
* **Standard output.** ``-`` (and ``/dev/stdout``, ``/dev/fd/1``, ``/proc/self/fd/1``) writes a text output
  (JSON, HTML, OpenDRIVE) to standard output; the command's own status line then goes to standard error, so
  the output can be piped (``/dev/stderr`` writes to standard error). A command that writes a folder or binary
  files refuses ``-``.
* **Regular files** are written to a temporary file beside them that is renamed onto them (atomic); an existing
  one is replaced only with ``--force``.
* **A FIFO** (named pipe) and ``/dev/null`` are written in place (opened and written, nothing renamed onto them);
  they need no ``--force`` since nothing is replaced. A FIFO must have its reader within 5 s of the write,
  else the write is refused (a plain open would wait forever).
* **A symbolic link** is refused, naming its target: genesis-rl neither replaces a link with a file nor writes
  through one (a link inside a shared campaign or run folder could point anywhere, e.g. at ``~/.bashrc``).
  Pass the target itself.
* **Any other special file** (a device other than ``/dev/null``, a socket) is refused.

``--force`` on a run, campaign or export folder replaces only what genesis-rl writes there (the folder kind's own
entries, ``output_folder.OWN_ENTRIES``) and refuses, naming them, when anything else is inside.
"""

from __future__ import annotations

import errno
import json
import os
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.ownership import check_overwrite, note_written
from genesis_rl.core.files.special_files import DISCARD, special_kind

#: names that mean standard output, and standard error
STDOUT_NAMES = ("-", "/dev/stdout", "/dev/fd/1", "/proc/self/fd/1")
STDERR_NAMES = ("/dev/stderr", "/dev/fd/2", "/proc/self/fd/2")

Inputs = Sequence["str | Path | None"]


def is_stdout(given: str | Path | None) -> bool:
    """Whether a path names a standard stream (standard output, or standard error), written in place."""
    return given is not None and str(given) in (*STDOUT_NAMES, *STDERR_NAMES)


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def check_inputs(out: str | Path, inputs: Inputs, *, flag: str = "--out", products: Sequence[str] = (),
                 folder: bool = False, nested_ok: bool = False, files: Sequence[str] | None = None) -> None:
    """Refuse an output that is one of the command's ``inputs``, holds one (``folder`` outputs), or lies inside
    an input folder, naming both as given. Inside an input folder an output is allowed only where its path
    relative to that folder matches one of ``products`` (regular expressions: what the command writes there
    by design), or anywhere with ``nested_ok`` (a folder output checked elsewhere not to land on what the
    command reads: evaluate's ``RUN/eval``). With ``files`` (drive, render, replay: the output folder gets these
    files added beside others) only an input that is the folder or one of those files is refused."""
    if is_stdout(out):
        return
    real = Path(os.path.realpath(out))
    for given in inputs:
        if given is None or is_stdout(given):
            continue
        if "\x00" in str(given):  # a path no system call takes (a NUL read from a shared campaign.json)
            raise UserInputError(f"input path {str(given)!r} holds a NUL byte, which no file name can; fix the "
                                 "file that names it")
        path = Path(os.path.realpath(given))
        if files is not None:
            if path == real or path in {real / f for f in files} or any(_same_file(real / f, path) for f in files):
                raise UserInputError(f"{flag} '{out}' would overwrite this command's input '{given}'; write the "
                                     "output somewhere else")
            continue
        if path == real or _same_file(real, path):
            raise UserInputError(f"{flag} '{out}' is this command's input '{given}'; write the output somewhere else")
        twin = _hard_link_inside(real, path)
        if twin is not None:
            raise UserInputError(f"{flag} '{out}' is a hard link to '{twin}', a file of this command's input "
                                 f"'{given}'; write the output somewhere else")
        if folder and real in path.parents:
            raise UserInputError(f"{flag} '{out}' holds this command's input '{given}'; write the output somewhere "
                                 "else")
        if path in real.parents and not nested_ok:
            rel = real.relative_to(path).as_posix()
            if any(re.fullmatch(p, rel) for p in products):
                continue
            entry = path / rel.split("/")[0]
            onto = f" (onto its '{entry.name}')" if os.path.lexists(entry) else ""
            raise UserInputError(f"{flag} '{out}' lies inside this command's input '{given}'{onto}; write the "
                                 "output somewhere else")


#: the most files of an input folder searched for a hard link of the output (a campaign holds a few per episode)
HARD_LINK_SEARCH = 200_000


def _hard_link_inside(out: Path, folder: Path) -> Path | None:
    """The file inside input ``folder`` that the existing output ``out`` is a hard link of, if any. Searched only
    when ``out`` has more than one link (``st_nlink``), so an ordinary output costs one ``stat``."""
    try:
        st = os.stat(out)
    except OSError:
        return None
    if st.st_nlink < 2 or not folder.is_dir():
        return None
    seen = 0
    for root, _dirs, names in os.walk(folder):
        for name in names:
            seen += 1
            if seen > HARD_LINK_SEARCH:
                return None
            try:
                other = os.stat(os.path.join(root, name), follow_symlinks=False)
            except OSError:
                continue
            if (other.st_dev, other.st_ino) == (st.st_dev, st.st_ino):
                return Path(root) / name
    return None


def check_folder_output(out: str | Path, flag: str = "--out") -> None:
    """A command that writes a folder cannot write it to standard output."""
    if is_stdout(out):
        raise UserInputError(f"{flag} '{out}': this command writes a folder of files; standard output ('-') is only "
                             "for a single text output (e.g. compare --json -, corners --out -)")


@dataclass(frozen=True)
class OutputFile:
    """Where a text output goes: standard output (``path`` None), a FIFO or /dev/null written in place
    (``in_place``), or a regular file written atomically."""
    given: str
    path: Path | None
    in_place: bool = False

    @property
    def to_stdout(self) -> bool:
        return self.path is None and self.given not in STDERR_NAMES

    @property
    def status(self) -> TextIO:
        """Where the command's own status line goes: standard error when the output takes standard output."""
        return sys.stderr if self.to_stdout else sys.stdout

    def __str__(self) -> str:
        return self.given if self.path is None else str(self.path)

    def write_text(self, text: str) -> None:
        from genesis_rl.core.files.io_utils import atomic_write_text

        if self.path is None:
            stream = sys.stdout if self.to_stdout else sys.stderr
            try:
                stream.write(text)
                stream.flush()
            except BrokenPipeError:  # the reader left (| head): say so once, without Python's exit-time noise
                devnull = os.open(os.devnull, os.O_WRONLY)
                try:
                    os.dup2(devnull, stream.fileno())
                except (OSError, ValueError):
                    pass
                os.close(devnull)
                raise OSError(errno.EPIPE, os.strerror(errno.EPIPE), self.given) from None
            return
        if self.in_place:
            with os.fdopen(_open_in_place(self.path), "w", encoding="utf-8") as f:
                f.write(text)
            return
        atomic_write_text(self.path, text)
        note_written(self.path)  # report.html into a campaign: listed in its manifest as the tool's

    def write_json(self, data: Any, indent: int | None = None) -> None:
        self.write_text(json.dumps(data, indent=indent, separators=None if indent else (",", ":")))


#: how long a FIFO output may wait for its reader to open it before the write is refused
FIFO_READER_WAIT_S = 5.0


def _open_in_place(path: Path) -> int:
    """A descriptor for writing a FIFO or /dev/null in place. A FIFO is opened without blocking, retried for
    ``FIFO_READER_WAIT_S``: a plain open would wait forever for a reader that never comes (a hung command)."""
    import fcntl
    import time

    deadline = time.monotonic() + FIFO_READER_WAIT_S
    while True:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
            break
        except OSError as err:
            if err.errno != errno.ENXIO:  # ENXIO: a FIFO nobody has open for reading (yet)
                raise
            if time.monotonic() >= deadline:
                raise UserInputError(f"output '{path}' is a FIFO that no process read within "
                                     f"{FIFO_READER_WAIT_S:g} s; start its reader first (e.g. `cat {path} &`), "
                                     "or write to a regular file") from None
            time.sleep(0.05)
    fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)  # a reader: block as usual
    return fd


def output_file(given: str | Path, force: bool, *, flag: str = "--out", inputs: Inputs = (),
                products: Sequence[str] = ()) -> OutputFile:
    """Check a text output the command is about to write (the module's rule) before any work starts, and
    return where it goes."""
    name = str(given)
    if is_stdout(name):
        return OutputFile(name, None)
    if not name:
        raise UserInputError(f"{flag} is empty; give a file path or '-' for standard output")
    path = Path(name)
    if name.endswith(("/", os.sep)) and not path.is_dir():  # Path() drops the slash: it would become a file
        raise UserInputError(f"{flag} '{name}' ends in '/', so it names a folder, and none is there; this command "
                             f"writes one file: give a file name (e.g. {name.rstrip('/' + os.sep) or 'out'}.json)")
    check_inputs(path, inputs, flag=flag, products=products)
    kind = special_kind(path)
    if kind == "FIFO (named pipe)" or (kind == "character device" and os.path.realpath(path) == DISCARD):
        return OutputFile(name, path, in_place=True)
    from genesis_rl.core.files.io_utils import ensure_writable

    ensure_writable(path, force)  # a folder, an existing file without --force, then a link or device
    if force and path.is_file():
        check_overwrite(path)  # CAMPAIGN/report.html edited by hand: named, not replaced
    return OutputFile(name, path)
