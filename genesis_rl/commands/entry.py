"""The console entry point: Ctrl-C while the command line is still importing its modules (about 0.4 s, more
on a busy machine) exits 130 with one line, as it does once the command runs, instead of a traceback; SIGTERM
exits 143 the same way (signals.py)."""

from __future__ import annotations

import sys


def main() -> int:
    from genesis_rl.core.signals import exit_status, interrupts_raise  # the standard library only: no delay

    # the process's own program (the genesis-rl script, python -m genesis_rl) ignores both signals once the
    # command has ended and its results are written: one during the interpreter's shut-down would kill a
    # finished command (status -15) or raise in an atexit hook; called from elsewhere (tests), the caller's
    # handlers come back
    own_process = getattr(sys.modules.get("__main__"), "main", None) is main
    try:
        with interrupts_raise(restore=not own_process):
            try:
                from genesis_rl.commands.cli import (
                    main as cli_main,  # local: the import itself is what Ctrl-C may interrupt
                )
            except KeyboardInterrupt as err:
                print("interrupted", file=sys.stderr)
                return exit_status(err)
            return cli_main()
    except KeyboardInterrupt as err:  # a signal in the instant between the command's end and the handlers' reset
        return exit_status(err)
