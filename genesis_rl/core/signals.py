"""Clean interrupts: SIGINT (Ctrl-C) and SIGTERM (``kill``, a batch scheduler, a container stopping) take the
same clean-up path, and a write in progress finishes before either takes effect.

- :class:`Interrupted` is what either signal raises under the command line (:func:`interrupts_raise`). It is
  a ``KeyboardInterrupt``, so every ``except KeyboardInterrupt``, ``except BaseException`` and ``finally``
  (temporary files, folder locks, a half-started run folder) runs for SIGTERM too, where SIGTERM's default
  action would kill the process on the spot; the command exits ``128 + signal`` (130, 143).
- :func:`deferred_signals` holds both signals for the short time a write must be whole (an atomic rename, a
  checkpoint's files and its ``last.json``, a row of ``episodes.csv``) and lets the first through as soon as
  the write ends. A second signal during the write goes through at once (the user insists); a library that
  turns it into its own error (``torch.save`` reports a ``KeyboardInterrupt`` in its writer as a
  ``RuntimeError``) is answered with :class:`Interrupted` all the same.

Both do nothing outside the main thread (Python runs signal handlers there only) and leave a signal that is
ignored (``nohup``) or handled outside Python as it is.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

#: the signals that end a command cleanly
SIGNALS: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)

_deferring = False


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; ``signum`` says which (the exit status is ``128 + signum``)."""

    def __init__(self, signum: int = signal.SIGINT) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def exit_status(err: BaseException) -> int:
    """The shell's status for a command ended by ``err``: 130 for Ctrl-C, 143 for SIGTERM."""
    return 128 + int(getattr(err, "signum", signal.SIGINT))


def resume_hint(err: BaseException) -> str | None:
    """What the interrupted command says the user can do next (set with :func:`set_resume_hint`)."""
    hint = getattr(err, "genesis_rl_hint", None)
    return hint if isinstance(hint, str) else None


def set_resume_hint(err: BaseException, hint: str) -> None:
    err.genesis_rl_hint = hint  # type: ignore[attr-defined]  # any exception object takes attributes


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise(signum: int, frame: Any) -> None:
    raise Interrupted(signum)


@contextmanager
def interrupts_raise(restore: bool = True) -> Iterator[None]:
    """For the block, SIGINT and SIGTERM raise :class:`Interrupted`; the previous handlers come back after
    (``cli.main`` is also called from tests and notebooks), or with ``restore`` False (the console entry
    point: the command has ended, its results are written) both are ignored while the process shuts down.
    A signal that is ignored or already has a handler of someone else's (a host program, an outer block)
    keeps it."""
    installed: dict[int, Any] = {}
    if _main_thread():
        for signum in SIGNALS:
            current = signal.getsignal(signum)
            if current is (signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL):
                installed[signum] = current
                signal.signal(signum, _raise)
    try:
        yield
    finally:
        for signum, handler in installed.items():
            signal.signal(signum, handler if restore else signal.SIG_IGN)


@contextmanager
def deferred_signals() -> Iterator[None]:
    """Hold SIGINT and SIGTERM until the block ends, then deliver the first one received to the handler that
    was in place (raising there, or ending the process where that is the signal's default action). Nested
    blocks are one block. Also a decorator: ``@deferred_signals()``."""
    global _deferring
    if _deferring or not _main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum: int, frame: Any) -> None:
        received.append(signum)
        if len(received) > 1:  # a second signal: the user insists, the write is abandoned (its temporary too)
            raise Interrupted(signum)

    previous: dict[int, Any] = {}
    for signum in SIGNALS:
        current = signal.getsignal(signum)
        if current is not None and current is not signal.SIG_IGN:  # None: a handler set outside Python
            previous[signum] = current
    _deferring = True
    try:
        for signum in previous:
            signal.signal(signum, hold)
        yield
    except BaseException as err:
        if len(received) > 1 and not isinstance(err, KeyboardInterrupt):
            raise Interrupted(received[-1]) from None  # a library's wrapping of it (torch: RuntimeError)
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _deferring = False
        if len(received) == 1:
            signal.raise_signal(received[0])  # the handler runs now, here, as if the signal came just now
