"""The console entry point: Ctrl-C while the command line is still importing its modules (about 0.4 s, more
on a busy machine) exits 130 with one line, as it does once the command runs, instead of a traceback."""

from __future__ import annotations

import sys


def main() -> int:
    try:
        from genesis_rl.cli import main as cli_main  # local: the import itself is what Ctrl-C may interrupt
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return cli_main()
