"""The ``genesis-rl`` command line: one module per command in this package, each exporting
``add_parser(subparsers)`` and ``run(args)``; this module groups them by the data flow and runs one.

Each command imports what it runs inside ``run`` (local imports on purpose): ``genesis-rl --help`` and a
mistyped flag answer in about half a second instead of the seconds that importing torch, Panda3D and the
campaign code costs."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import textwrap
import warnings
from typing import Any

from genesis_rl import __version__
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import os_error_message
from genesis_rl.core.plugins import import_env_plugins
from genesis_rl.core.signals import exit_status, interrupts_raise, resume_hint
from genesis_rl.core.text import terminal_safe
from genesis_rl.core.trust import add_trust_arguments, trusted_for

#: the commands in the order of the data flow, each group a stage (its module: genesis_rl/commands/NAME.py)
GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("world and simulator", ("scenes", "map", "render", "drive")),
    ("system under test", ("detector", "models", "realism")),
    ("train the adversary", ("train",)),
    ("campaigns and their analysis", ("evaluate", "report", "compare", "replay", "reactivity", "corners")),
    ("benchmark on known weaknesses", ("zoo", "benchmark")),
    ("failure rates and retraining", ("estimate", "harden")),
    ("export", ("export",)),
    ("tools", ("speed",)),
)
COMMANDS: tuple[str, ...] = tuple(name for _, names in GROUPS for name in names)


def command_module(name: str) -> Any:
    """The module of command ``name`` (``genesis_rl.commands.NAME``)."""
    return importlib.import_module(f"genesis_rl.commands.{name}")


class Parser(argparse.ArgumentParser):
    """argparse's parser, except that a help or version text that cannot be written (a full disk, a closed pipe)
    is an error: argparse itself swallows the OSError and exits 0 with nothing written."""

    def _print_message(self, message: str, file: Any = None) -> None:
        if message:
            (file or sys.stderr).write(message)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="genesis-rl",
        description="GENESIS-RL: find natural edge cases for autonomous driving by turning the weather.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"genesis-rl {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="<command>", help=argparse.SUPPRESS)
    for name in COMMANDS:
        command_module(name).add_parser(sub)
    helps = {action.dest: action.help or "" for action in sub._choices_actions}
    for choice, page in sub.choices.items():  # each command's own --help opens with its one-line summary
        page.description = page.description or helps.get(choice, "")
    width = max(len(n) for n in COMMANDS) + 2
    lines = ["commands, in the order the data flows (genesis-rl <command> --help for each):"]
    for title, names in GROUPS:
        lines.append(f"\n  {title}:")
        for n in names:  # a long summary wraps under itself, not under the names
            wrapped = textwrap.wrap(helps[n], 100 - 4 - width) or [""]
            lines += [f"    {n:<{width}}{wrapped[0]}", *(" " * (4 + width) + w for w in wrapped[1:])]
    lines.append("\nquick start: bash scripts/quickstart.sh (README.md); what each writes: docs/")
    p.epilog = "\n".join(lines)
    add_trust_arguments({name: sub.choices[name] for name in COMMANDS})  # aliases share their parser
    return p


def _one_line_warning(command: str, default: Any) -> Any:
    """The package's own warnings as one line naming the command (Python's format adds the file, line number
    and the source line of the warn call: noise to a user); other libraries' warnings keep their format."""
    def format_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                       line: str | None = None) -> str:
        if f"{os.sep}genesis_rl{os.sep}" in filename:
            return f"genesis-rl {command}: warning: {terminal_safe(str(message))}\n"
        return str(default(message, category, filename, lineno, line))

    return format_warning


def main(argv: list[str] | None = None) -> int:
    named: list[str] = []  # the subcommand, once parsed
    try:
        with interrupts_raise():  # SIGTERM cleans up as Ctrl-C does, from the first line on (signals.py)
            return _main(argv, named)
    except KeyboardInterrupt as err:  # one line, what to do next where the command knows it
        hint = resume_hint(err)
        print(" ".join(["genesis-rl", *named]) + ": interrupted" + (f"; {hint}" if hint else ""), file=sys.stderr)
        return exit_status(err)


def _main(argv: list[str] | None, named: list[str]) -> int:
    try:
        import_env_plugins()  # before the parser: a user's knobs are known to --weather and --help
    except UserInputError as err:
        print(f"genesis-rl: error: {terminal_safe(str(err))}", file=sys.stderr)
        return err.exit_code
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UserInputError as err:  # a count flag out of its bounds (cli_args.count)
        names = next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # aliases too
        command = next((a for a in (sys.argv[1:] if argv is None else argv) if a in names), None)
        print(" ".join(["genesis-rl", *([command] if command else [])]) + f": error: {terminal_safe(str(err))}",
              file=sys.stderr)
        return err.exit_code
    except OSError as err:  # --help or --version to a full disk or a closed pipe (Parser above)
        print(f"genesis-rl: error: the help or version text could not be written ({err.strerror or err})",
              file=sys.stderr)
        return UserInputError.exit_code
    named.append(args.command)
    default_format = warnings.formatwarning
    warnings.formatwarning = _one_line_warning(args.command, default_format)
    try:
        with trusted_for(args):  # only what this command line names is imported or unpickled
            return int(args.func(args))
    except UserInputError as err:
        print(f"genesis-rl {args.command}: error: {terminal_safe(str(err))}", file=sys.stderr)
        return err.exit_code
    except OSError as err:  # permission, read-only, disk full, name too long: the machine's, not a bug
        message = os_error_message(err)
        if message is None:
            raise
        print(f"genesis-rl {args.command}: error: {terminal_safe(message)}", file=sys.stderr)
        return UserInputError.exit_code
    finally:
        warnings.formatwarning = default_format

