"""What a command may run that a file names: the command line decides, never the file.

Run folders, campaigns and records are shared between people, so opening one must be as safe as opening a
CSV. Two things in such files could run code: an import path (a system, rule, policy, backend or
``env.plugins`` module) and a pickle (SB3 keeps its schedules, spaces and last observation pickled inside
an agent's ``data``; older checkpoints kept SAC's replay buffer as a pickle). While a command runs:

- an import path from a file resolves only to a module the command line names (``--plugin MODULE``,
  ``GENESIS_RL_PLUGINS``, or the module of an import path given to ``--system``, ``--backend`` or
  ``--policies``) or to the package's own (genesis_rl/core/plugins.py holds the gate);
- nothing is unpickled unless ``--trust-pickle`` is given (training/safe_load.py loads agents and
  checkpoints without it). Both reach spawned worker processes through the environment.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.plugins import PLUGINS_VARIABLE, gate, import_modules, module_of

#: Set to "1" while a command given ``--trust-pickle`` runs (and so in its spawned workers).
PICKLE_VARIABLE = "GENESIS_RL_TRUST_PICKLE"

#: Set while a command runs: a JSON list of the files its command line names (``--weights``), resolved.
FILES_VARIABLE = "GENESIS_RL_NAMED_FILES"

#: Subcommands that open an agent or a checkpoint, and so take ``--trust-pickle``.
PICKLE_COMMANDS = ("train", "evaluate", "reactivity")


def add_trust_arguments(commands: Mapping[str, argparse.ArgumentParser]) -> None:
    """``--plugin`` on every subcommand, ``--trust-pickle`` on those that open agents or checkpoints."""
    for name, parser in commands.items():
        parser.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                            help="import MODULE first (it may register knobs, rules, policies) and let import paths "
                                 "into it that a file names (a run's config.toml, a campaign.json, a record, a "
                                 "rulebook) load; repeat or comma-separate for more. Without it, code a file names "
                                 "is never imported")
        if name in PICKLE_COMMANDS:
            parser.add_argument("--trust-pickle", action="store_true",
                                help="let an agent or checkpoint written by an older genesis-rl load through pickle "
                                     "(unpickling runs any code the file holds: only for files you trust)")


def plugin_modules(args: argparse.Namespace) -> list[str]:
    """The modules named by ``--plugin`` (MODULE or MODULE:Class, comma lists)."""
    out = []
    for item in getattr(args, "plugin", None) or []:
        for name in str(item).split(","):
            name = name.strip()
            if name:
                out.append(module_of(name) or name)
    return out


def named_modules(args: argparse.Namespace) -> set[str]:
    """Every module this command line names: ``--plugin``, ``GENESIS_RL_PLUGINS`` and the modules of import
    paths given to ``--system``, ``--backend``, ``--policies`` and ``--retrain``."""
    names = set(plugin_modules(args))
    names |= {n.strip() for n in os.environ.get(PLUGINS_VARIABLE, "").split(",") if n.strip()}
    for flag in ("system", "backend", "policies", "policy", "retrain"):
        value = getattr(args, flag, None)
        if isinstance(value, str):
            names |= {m for m in (module_of(v.strip()) for v in value.split(",")) if m}
    return names


@contextmanager
def trusted_for(args: argparse.Namespace) -> Iterator[None]:
    """Run a command under its own trust: the gate on imports, ``--trust-pickle`` or not (an ambient
    variable does not count), and the ``--plugin`` modules imported."""
    import json
    from pathlib import Path

    saved = {v: os.environ.pop(v, None) for v in (PICKLE_VARIABLE, FILES_VARIABLE)}
    if getattr(args, "trust_pickle", False):
        os.environ[PICKLE_VARIABLE] = "1"
    weights = getattr(args, "weights", None)
    os.environ[FILES_VARIABLE] = json.dumps([str(Path(weights).resolve())] if isinstance(weights, str) else [])
    try:
        with gate(named_modules(args)):
            import_modules(plugin_modules(args), "--plugin")
            yield
    finally:
        for variable, value in saved.items():
            os.environ.pop(variable, None)
            if value is not None:
                os.environ[variable] = value


def pickle_trusted() -> bool:
    """Whether this command was given ``--trust-pickle`` (in this process or the command's parent)."""
    return os.environ.get(PICKLE_VARIABLE) == "1"


def check_pickle_file(path: str | os.PathLike[str], what: str) -> None:
    """Refuse to load ``path``, a file format that is a pickle (a YOLO ``.pt``), unless the command line
    names it (``--weights``), the command has ``--trust-pickle``, or no command runs (the Python API): a path
    read from a run's config.toml, a campaign.json or a record is not reason enough to run what it holds."""
    import json
    from pathlib import Path

    text = os.environ.get(FILES_VARIABLE)
    if text is None or pickle_trusted():
        return
    try:
        named = set(json.loads(text))
    except (ValueError, TypeError):
        named = set()
    if str(Path(path).resolve()) in named:
        return
    raise UserInputError(f"{what} '{path}' comes from a file (a run's config.toml, a campaign.json or a record), "
                         "and loading it unpickles it, which runs any code it holds: pass --weights PATH on the "
                         "command line, or --trust-pickle where the command has it, if you trust the file")
