"""Guarded import of the optional ``carla`` client, so a missing extra fails with the command that fixes it."""

from __future__ import annotations

from types import ModuleType

from genesis_rl.core.errors import UserInputError

INSTALL_HINT = (
    "the CARLA backend needs the 'carla' client package (0.9.16, Python 3.11, Linux x86_64 or Windows): "
    "pip install -e .[carla]   (or: pip install carla==0.9.16)"
)


def require_carla() -> ModuleType:
    """The ``carla`` module, or a :class:`UserInputError` naming the install command."""
    try:
        import carla
    except ImportError as err:
        raise UserInputError(f"{INSTALL_HINT} ({err})") from None
    return carla
