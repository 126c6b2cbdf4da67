"""One place that turns a backend name (``lite`` or ``carla``) and its connection flags into a Backend, so
every command takes ``--backend carla --carla-host H --carla-port P`` the same way."""

from __future__ import annotations

import argparse

from genesis_rl.errors import UserInputError
from genesis_rl.sim.interface import Backend

BACKENDS = ("lite", "carla")


def add_backend_arguments(parser: argparse.ArgumentParser, default: str | None = "lite") -> None:
    """``--backend`` and the CARLA connection flags (ignored by ``lite``); ``default=None`` lets a config
    file's ``env.backend`` decide unless the flag is given."""
    parser.add_argument("--backend", default=default, choices=BACKENDS,
                        help="simulator: lite (embedded) or carla (a running CARLA 0.9.16 server, see docs/carla.md)")
    parser.add_argument("--carla-host", default="localhost", help="CARLA server host (--backend carla)")
    parser.add_argument("--carla-port", type=int, default=2000, help="CARLA server RPC port (--backend carla)")
    parser.add_argument("--carla-tm-port", type=int, default=8000, help="CARLA traffic manager port (--backend carla)")
    parser.add_argument("--carla-timeout", type=float, default=10.0,
                        help="seconds to wait for the CARLA server on each call (--backend carla)")


def make_backend(name: str, *, carla_host: str = "localhost", carla_port: int = 2000, carla_tm_port: int = 8000,
                 carla_timeout: float = 10.0) -> Backend:
    """A connected backend; ``carla`` fails here, with host:port and what to do, when no server answers."""
    if name == "lite":
        from genesis_rl.lite.backend import LiteBackend

        return LiteBackend()
    if name == "carla":
        from genesis_rl.carla_backend.backend import CarlaBackend

        return CarlaBackend(carla_host, carla_port, carla_timeout, carla_tm_port)
    raise UserInputError(f"--backend '{name}' is unknown; allowed: {', '.join(BACKENDS)}")


def backend_from_args(args: argparse.Namespace) -> Backend:
    return make_backend(args.backend, carla_host=args.carla_host, carla_port=args.carla_port,
                        carla_tm_port=args.carla_tm_port, carla_timeout=args.carla_timeout)
