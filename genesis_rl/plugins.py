"""Plug-ins named by import path: one helper turns ``package.module:Class`` into a class, with the same
errors for every kind of plug-in (systems under test, weather policies, backends).

Each kind keeps its built-in names (``builtin``, ``lite``, ...) in a table of import paths; a user's own
class is named the same way, so nothing of the package is edited to add one.
"""

from __future__ import annotations

import importlib
import inspect
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from genesis_rl.errors import UserInputError


def load_class(spec: str, kind: str, builtins: Mapping[str, str], *, base: type | None = None,
               methods: Sequence[str] = (), protocol: str = "") -> type[Any]:
    """The class that ``spec`` names: a built-in name (a key of ``builtins``, mapped to its import path) or
    ``package.module:Class``.

    ``kind`` names the plug-in in errors ("system", "backend"). The class must subclass ``base`` when given
    and have the callable ``methods`` of its protocol (``protocol`` names the module that defines it).
    Errors name what is wrong: a malformed path, a module that does not import, a missing class, a class
    of the wrong kind.
    """
    path = builtins.get(spec, spec)
    if ":" not in path:
        raise UserInputError(f"{kind} '{spec}' is not an import path 'package.module:Class' nor a built-in "
                             f"({', '.join(builtins)})")
    module_name, _, class_name = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except Exception as err:  # noqa: BLE001 - any import failure is the user's to see
        raise UserInputError(f"{kind} '{spec}': cannot import module '{module_name}': {err}") from None
    cls = getattr(module, class_name, None)
    if cls is None or not inspect.isclass(cls):
        raise UserInputError(f"{kind} '{spec}': module '{module_name}' has no class '{class_name}'")
    if base is not None and not issubclass(cls, base):
        raise UserInputError(f"{kind} '{spec}': class {class_name} is not a {base.__module__}.{base.__qualname__} "
                             "subclass")
    missing = [m for m in methods if not callable(getattr(cls, m, None))]
    if missing:
        raise UserInputError(f"{kind} '{spec}': class {class_name} lacks the protocol's methods: "
                             f"{', '.join(missing)} (a {kind} needs {', '.join(methods)}; see {protocol})")
    return cls


def user_modules(classes: Iterable[type], modules: Iterable[str] = ()) -> list[str]:
    """The user modules among the modules that define ``classes`` (registered plug-ins: policies, rules) and
    ``modules`` (those that declared knobs): a spawned worker process imports them again, so what they
    registered resolves there too. The package's own modules and a ``__main__`` script (which the spawn start
    method re-runs itself) are left out."""
    names = {c.__module__ for c in classes} | set(modules)
    return sorted(m for m in names if m and m != "genesis_rl" and not m.startswith("genesis_rl.")
                  and m not in ("__main__", "__mp_main__"))


def import_modules(names: Iterable[str], field: str = "plugins") -> None:
    """Import each module: user modules that register plug-ins at import (``register_knob``,
    ``@register_policy``, ``@register_rule``), named by ``env.plugins`` or ``GENESIS_RL_PLUGINS``, and, in a
    worker process, those its parent had imported. ``field`` names the setting in errors."""
    for name in names:
        try:
            importlib.import_module(name)
        except Exception as err:  # noqa: BLE001 - any import failure is the user's to see
            raise UserInputError(f"{field}: cannot import module '{name}': {err}") from None


#: Environment variable: comma-separated modules the command line imports before it reads its arguments
#: (so a knob a module declares is known to ``--weather`` and ``--help``).
PLUGINS_VARIABLE = "GENESIS_RL_PLUGINS"


def import_env_plugins() -> None:
    names = [n.strip() for n in os.environ.get(PLUGINS_VARIABLE, "").split(",") if n.strip()]
    import_modules(names, PLUGINS_VARIABLE)
