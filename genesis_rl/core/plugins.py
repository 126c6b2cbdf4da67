"""Plug-ins named by import path: one helper turns ``package.module:Class`` into a class, with the same
errors for every kind of plug-in (systems under test, weather policies, backends).

Each kind keeps its built-in names (``builtin``, ``lite``, ...) in a table of import paths; a user's own
class is named the same way, so nothing of the package is edited to add one.

Importing a module runs its code, so the command line decides what may be imported (docs/reliability.md,
"Safe loading"): while a command runs, :func:`gate` holds the modules the user named *now* (``--plugin``,
``GENESIS_RL_PLUGINS``, an import path given to ``--system``, ``--backend`` or ``--policies``), and an import path
read from a file (a run's config.toml, a campaign.json, a record, a rulebook) resolves only to those modules
or the package's own; anything else is refused, naming ``--plugin``. Spawned worker processes inherit the
gate through the environment. Outside a command (the Python API) nothing is gated: the caller runs code
already.
"""

from __future__ import annotations

import importlib
import inspect
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from genesis_rl.core.errors import UserInputError

#: Environment variable that carries the gate into spawned worker processes: a JSON list of the trusted
#: modules (set only while a command runs; absent: no gate).
GATE_VARIABLE = "GENESIS_RL_TRUSTED_MODULES"


def _trusted() -> set[str] | None:
    """The modules the user named for this command, or None when no command holds the gate."""
    import json

    text = os.environ.get(GATE_VARIABLE)
    if text is None:
        return None
    try:
        names = json.loads(text)
    except ValueError:
        return set()
    return {n for n in names if isinstance(n, str)} if isinstance(names, list) else set()


def gate_held() -> bool:
    """Whether a command holds the gate (in this process or the command's parent)."""
    return GATE_VARIABLE in os.environ


#: the package's layers that hold what a file may name: systems, rules, policies, backends, knobs, the env
PLUGIN_LAYERS = ("genesis_rl.world", "genesis_rl.sim", "genesis_rl.sut", "genesis_rl.loop", "genesis_rl.env",
                 "genesis_rl.labels", "genesis_rl.adversaries")


def _own(module: str) -> bool:
    """Whether ``module`` is one of the package's plug-in layers (an old path counts as its new one). Not any
    ``genesis_rl.*`` module: the command line (``genesis_rl.__main__``, ``genesis_rl.commands``) and the
    stages above the adversaries are never what a file needs to name."""
    from genesis_rl.compat import new_path

    module = new_path(module) or module
    return any(module == layer or module.startswith(layer + ".") for layer in PLUGIN_LAYERS)


def import_allowed(module: str) -> bool:
    """Whether :func:`check_import` lets ``module`` in."""
    trusted = _trusted()
    return trusted is None or _own(module) or module in trusted


def check_import(module: str, what: str) -> None:
    """Refuse to import ``module`` (named by ``what``, e.g. "system 'evil:Sys'") unless no gate is held, it
    is the package's own, or the user named it on the command line of this command."""
    trusted = _trusted()
    if trusted is None or _own(module) or module in trusted:
        return
    raise UserInputError(f"{what}: module '{module}' is not one the command line names; an import path read "
                         "from a file (a run's config.toml, a campaign.json, a record or a rulebook) is not "
                         f"imported, since importing runs its code: pass --plugin {module} if you trust it")


def module_of(spec: str) -> str | None:
    """The module of an import path ``package.module:Class`` (None for a plain name)."""
    return spec.partition(":")[0] if ":" in spec else None


class gate:  # noqa: N801 - used as a context manager, like a function
    """While a command runs: only ``modules`` (and the package's own) may be imported by a name from a file.
    Nested gates add their modules; leaving restores the previous state (the environment variable)."""

    def __init__(self, modules: Iterable[str]) -> None:
        self.modules = sorted({m for m in modules if m})
        self.saved: str | None = None

    def __enter__(self) -> gate:
        import json

        self.saved = os.environ.get(GATE_VARIABLE)
        os.environ[GATE_VARIABLE] = json.dumps(sorted(set(self.modules) | (_trusted() or set())))
        return self

    def __exit__(self, *exc: object) -> None:
        if self.saved is None:
            os.environ.pop(GATE_VARIABLE, None)
        else:
            os.environ[GATE_VARIABLE] = self.saved


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
    module = _import_named(module_name, kind, spec, checked=spec not in builtins)
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


def load_function(spec: str, kind: str) -> Any:
    """The function ``package.module:function`` names (a user's hook), its module gated as every plug-in's."""
    module_name, _, func_name = spec.partition(":")
    module = _import_named(module_name, kind, spec)
    func = getattr(module, func_name, None)
    if func is None or not callable(func) or inspect.isclass(func):
        raise UserInputError(f"{kind} '{spec}': module '{module_name}' has no function '{func_name}'")
    return func


def _import_named(module_name: str, kind: str, spec: str, checked: bool = True) -> Any:
    """Import the module of plug-in ``spec`` (the gate first, unless a built-in's); errors name both."""
    if checked:
        check_import(module_name, f"{kind} '{spec}'")
    try:
        return importlib.import_module(module_name)
    except Exception as err:  # noqa: BLE001 - any import failure is the user's to see
        raise UserInputError(f"{kind} '{spec}': cannot import module '{module_name}': {err}") from None


def user_modules(classes: Iterable[type], modules: Iterable[str] = ()) -> list[str]:
    """The user modules among the modules that define ``classes`` (registered plug-ins: policies, rules) and
    ``modules`` (those that declared knobs): a spawned worker process imports them again, so what they
    registered resolves there too. The package's own modules and a ``__main__`` script (which the spawn start
    method re-runs itself) are left out."""
    names = {c.__module__ for c in classes} | set(modules)
    return sorted(m for m in names if m and m != "genesis_rl" and not m.startswith("genesis_rl.")
                  and m not in ("__main__", "__mp_main__"))


def import_modules(names: Iterable[str], field: str = "plugins", *, checked: bool = True) -> None:
    """Import each module: user modules that register plug-ins at import (``register_knob``,
    ``@register_policy``, ``@register_rule``), named by ``env.plugins`` or ``GENESIS_RL_PLUGINS``, and, in a
    worker process, those its parent had imported (``checked=False``: the parent's gate let them in; the
    names come from its memory, not from a file). ``field`` names the setting in errors."""
    for name in names:
        if checked:
            check_import(name, field)
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
