"""argparse types shared by every subcommand, so a bad value fails the same way (exit 2, the flag named)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.limits import Limit


def count(low: int = 1, limit: Limit | None = None) -> type[argparse.Action]:
    """``action=count(1, limits.SIM_STEPS)`` beside ``type=int``: a count flag's bounds, declared where the flag
    is. A value below ``low`` or over the limit (which its environment variable may raise) is refused as the
    flag is parsed, naming it and what is allowed (exit 2), before any command has imported or written
    anything. (A ``UserInputError``, not an argparse type error: argparse would replace a ValueError's message
    with "invalid value".)"""

    class Count(argparse.Action):
        def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                     values: str | Sequence[Any] | None, option_string: str | None = None) -> None:
            flag = option_string or self.dest
            value = int(values)  # type: ignore[arg-type] # type=int converted it
            if value < low:
                raise UserInputError(f"{flag} = {value}; allowed: an integer >= {low}")
            if limit is not None:
                limit.check(value, flag)
            setattr(namespace, self.dest, value)

    return Count

#: ``type=int, action=SEED``: a seed flag, an integer >= 0 (numpy's generators refuse negative seeds, and would
#: do so with a traceback), refused as count flags are, naming the flag
SEED = count(0)


def add_odd_arguments(parser: argparse.ArgumentParser) -> None:
    """``--odd FILE`` and ``--dynamics``: the operational design domain and how fast the weather may change
    (docs/odd.md); both override a config's or a trained agent's ``[env]``."""
    parser.add_argument("--odd", default=None, metavar="FILE",
                        help="operational design domain (configs/odd/*.toml): every policy is kept inside it and "
                             "every step and failure is labelled inside / boundary / outside")
    parser.add_argument("--odd-label-only", action="store_true",
                        help="label steps and failures against --odd without keeping the policy inside it (to audit "
                             "what a policy does when nothing holds it back)")
    parser.add_argument("--dynamics", default=None, choices=["paper", "natural"],
                        help="paper: a knob moves 5%% of its range per step; natural: at most what outdoor weather "
                             "does per second (the sun is held)")


def odd_overrides_from_args(args: argparse.Namespace) -> dict[str, str | bool]:
    """The ``[env]`` keys ``--odd`` and ``--dynamics`` set; the ODD path is made absolute so that a run's
    workers and a later ``--resume`` find it from any folder."""
    from pathlib import Path

    out: dict[str, str | bool] = {}
    if args.odd_label_only and args.odd is None:
        from genesis_rl.core.errors import UserInputError

        raise UserInputError("--odd-label-only needs --odd FILE (the domain to label against)")
    if args.odd is not None:
        out["odd"] = str(Path(args.odd).resolve())
        out["odd_keep_inside"] = not args.odd_label_only
    if args.dynamics is not None:
        out["dynamics"] = args.dynamics
    return out


def add_scale_arguments(parser: argparse.ArgumentParser, parallel: str) -> None:
    """``--executor``, ``--ray-address`` and ``--carla-servers``: where the ``parallel`` processes (``--workers``
    or ``--envs``) run, and which CARLA server each drives (docs/scaling.md)."""
    parser.add_argument("--executor", default="local", choices=["local", "ray"],
                        help=f"where the {parallel} run: local processes, or Ray actors (pip install -e .[ray])")
    parser.add_argument("--ray-address", default=None, metavar="ADDR",
                        help="Ray cluster to join (HOST:PORT, ray://HOST:PORT or auto; default: a local Ray)")
    parser.add_argument("--carla-servers", default=None, metavar="HOST:PORT[:TM],...",
                        help=f"--backend carla: one server per process of {parallel} (traffic manager at PORT+6000 "
                             "unless given)")
