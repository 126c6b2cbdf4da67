"""``python -m genesis_rl``: the command line. Importing this module runs nothing."""

from genesis_rl.commands.entry import main

if __name__ == "__main__":
    raise SystemExit(main())
