"""The backends, declared once: every command, the env and the catalog loader read them from here.

A backend is a :class:`~genesis_rl.sim.interface.Backend` subclass. The built-in ones are named in
:data:`BACKENDS` (what ``--backend`` and ``env.backend`` take, with their import path, their scene module and
a line for ``--help``); any other is named by its import path ``package.module:Class``, as systems and
policies are, and drives the catalogs of the built-in backend its ``catalog_kind`` names (a subclass of
``LiteBackend`` drives lite catalogs). See docs/extending.md.

A scene module (:class:`SceneSource`) makes a backend's catalogs and checks a loaded catalog against what
the schema cannot see (the lite maps' lanes); :func:`load_catalog` runs those checks, so load catalogs here.
The registry names modules by import path, so importing it (the CLI does, to build ``--help``) costs nothing.
"""

from __future__ import annotations

import argparse
import importlib
import math
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol, cast

from genesis_rl.core import ranges
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.hashing import regular_file_sha256
from genesis_rl.core.parsing import CATALOG_MB, check_size
from genesis_rl.core.plugins import load_class
from genesis_rl.sim.interface import Backend, ConnectionSettings
from genesis_rl.world.scenes.catalog import Catalog, parse_catalog, read_catalog


@dataclass(frozen=True)
class BackendEntry:
    """A built-in backend: its name, its Backend class and its scene module (import paths), and what
    ``--help`` says of it."""

    name: str
    target: str  # package.module:Class of its Backend subclass
    scenes: str  # module of its scene catalogs: a SceneSource
    description: str
    docs: str = ""  # the page that says how to set it up, named in errors


#: The built-in backends. Adding one: its Backend subclass, its scene module, and one line here.
BACKENDS: dict[str, BackendEntry] = {
    e.name: e
    for e in (
        BackendEntry("lite", "genesis_rl.sim.lite.backend:LiteBackend", "genesis_rl.sim.lite.scenes",
                     "embedded: lane-graph maps, kinematic traffic, Panda3D camera"),
        BackendEntry("carla", "genesis_rl.sim.carla.backend:CarlaBackend", "genesis_rl.sim.carla.scenes",
                     "a running CARLA 0.9.16 server, see docs/carla.md", docs="docs/carla.md"),
    )
}

#: scenes a command generates itself when given no catalog (~5 ms each; beyond this, make a catalog once)
MAX_GENERATED_ON_THE_FLY = 5000


class SceneSource(Protocol):
    """The module-level functions of a backend's scene module."""

    def check_map(self, map_name: str, field: str) -> None:
        """Fail (naming ``field``) when ``map_name`` is not a map of this backend, where that is known offline."""

    def default_count(self, map_name: str) -> int:
        """Scenes in a catalog of ``map_name`` when no count is given."""

    def generate(self, map_name: str, count: int, seed: int, settings: ConnectionSettings,
                 progress: bool = False) -> Catalog:
        """A catalog of ``count`` scenes; scene i depends only on (map, seed, i)."""

    def check_catalog(self, catalog: Catalog) -> None:
        """Fail on what the schema cannot check: the catalog against this backend's maps."""


def backend_help() -> str:
    """``--backend``'s help: each built-in backend with its line, then the import-path form."""
    return "simulator: " + "; ".join(f"{e.name} ({e.description})" for e in BACKENDS.values()) + \
        "; or package.module:Class of a Backend subclass"


def _allowed() -> str:
    return f"{', '.join(BACKENDS)} or package.module:Class"


def _named(setting: str, spec: str) -> str:
    """How an error names the value of a flag (``--backend 'x'``) or of a config key (``env.backend = 'x'``)."""
    return f"{setting} '{spec}'" if setting.startswith("--") else f"{setting} = '{spec}'"


def backend_class(spec: str, setting: str = "--backend") -> type[Backend]:
    """The Backend class of a built-in name or an import path; ``setting`` names the flag or config key in
    errors (``env.backend``)."""
    if spec in BACKENDS or ":" in spec:
        cls = load_class(spec, setting, {k: e.target for k, e in BACKENDS.items()}, base=Backend)
        if cls.catalog_kind not in BACKENDS:
            raise UserInputError(f"{_named(setting, spec)}: its catalog_kind '{cls.catalog_kind}' is not a built-in "
                                 f"backend's; allowed: {', '.join(BACKENDS)}")
        return cls
    raise UserInputError(f"{_named(setting, spec)} is unknown; allowed: {_allowed()}")


def scene_source(catalog_kind: str) -> SceneSource:
    """The scene module of the built-in backend whose catalogs these are."""
    if catalog_kind not in BACKENDS:
        raise UserInputError(f"catalog field 'backend' = '{catalog_kind}'; allowed: {', '.join(BACKENDS)}")
    module: ModuleType = importlib.import_module(BACKENDS[catalog_kind].scenes)
    return cast(SceneSource, module)


def check_backend_setting(spec: str, catalog: str | None, setting: str, catalog_setting: str) -> type[Backend]:
    """The backend's class, after checking that it is known and has a catalog when it needs one
    (``setting`` and ``catalog_setting`` name the flags or keys in errors: ``--backend``, ``--catalog``)."""
    cls = backend_class(spec, setting)
    if cls.needs_catalog and not catalog:
        entry = BACKENDS.get(spec)
        see = f" (see {entry.docs})" if entry and entry.docs else ""
        raise UserInputError(f"{_named(setting, spec)} needs {catalog_setting}: a catalog made with genesis-rl "
                             f"scenes --backend {spec}{see}")
    return cls


def make_backend(spec: str, settings: ConnectionSettings | None = None) -> Backend:
    """A connected backend; ``carla`` fails here, with host:port and what to do, when no server answers."""
    return backend_class(spec).from_settings(settings or ConnectionSettings())


# -- command-line flags -------------------------------------------------------------------------------------
def _backend_name(spec: str) -> str:
    """argparse's check of ``--backend`` (a typo fails at once; an import path is loaded when used)."""
    if spec not in BACKENDS and ":" not in spec:
        raise argparse.ArgumentTypeError(f"'{spec}' is unknown; allowed: {_allowed()}")
    return spec


def add_backend_arguments(parser: argparse.ArgumentParser, default: str | None = "lite") -> None:
    """``--backend`` and the connection flags (ignored by ``lite``); ``default=None`` lets a config file's
    ``env.backend`` decide unless the flag is given."""
    parser.add_argument("--backend", default=default, type=_backend_name, help=backend_help())
    parser.add_argument("--carla-host", default="localhost", help="CARLA server host (--backend carla)")
    parser.add_argument("--carla-port", type=_ports, default=(2000,), metavar="PORT[,PORT...]",
                        help="CARLA server RPC port (--backend carla); a list names one server per worker or env "
                             "process on --carla-host (traffic managers at PORT+6000), as --carla-servers does")
    parser.add_argument("--carla-tm-port", type=_port, default=None,
                        help="CARLA traffic manager port, 1..65535, opened on this machine (--backend carla); "
                             "default: --carla-port + 6000, so runs on other servers never share one")
    parser.add_argument("--carla-timeout", type=_timeout, default=10.0,
                        help="seconds to wait for the CARLA server on each call, 0.1..3600 (--backend carla)")


def _port(text: str) -> int:
    """``--carla-tm-port``: a TCP port 1..65535."""
    t = str(text).strip()
    if not t.isdigit() or not 1 <= int(t) <= 65535:
        raise argparse.ArgumentTypeError(f"'{text}': allowed: a TCP port 1..65535")
    return int(t)


def _timeout(text: str) -> float:
    """``--carla-timeout``: seconds in [0.1, 3600] (``inf`` would become 0 s in the client, ``nan`` never end)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and ranges.TIMEOUT.low <= value <= ranges.TIMEOUT.high):
        raise argparse.ArgumentTypeError(f"'{text}': allowed: {ranges.TIMEOUT.describe()}")
    return value


def _ports(text: str) -> tuple[int, ...]:
    """``--carla-port``: one port or a comma list (one server per process)."""
    items = [t.strip() for t in str(text).split(",")]
    if "" in items:  # 2000,,2001: a server left out by mistake, not a list of two
        raise argparse.ArgumentTypeError(f"'{text}' has an empty item; allowed: a TCP port 1..65535 or a comma "
                                         "list of them (e.g. 2000,3000)")
    if not items or not all(t.isdigit() and 1 <= int(t) <= 65535 for t in items):
        raise argparse.ArgumentTypeError(f"'{text}': allowed: a TCP port 1..65535 or a comma list of them "
                                         "(e.g. 2000,3000)")
    if len(set(items)) < len(items):
        raise argparse.ArgumentTypeError(f"'{text}' names a port twice; each process needs a server of its own")
    return tuple(int(t) for t in items)


def servers_text(args: argparse.Namespace) -> str | None:
    """The ``--carla-servers`` list, also when ``--carla-port`` names several ports on ``--carla-host``."""
    ports = tuple(getattr(args, "carla_port", (2000,)))
    servers = getattr(args, "carla_servers", None)
    if len(ports) > 1:
        if servers is not None:
            raise UserInputError("--carla-port names several servers and --carla-servers names them too; give one")
        return ",".join(f"{args.carla_host}:{p}" for p in ports)
    return servers


def settings_from_args(args: argparse.Namespace) -> ConnectionSettings:
    """The connection of a single process: the first of ``--carla-port``'s servers."""
    _check_connection_flags(args)
    return ConnectionSettings(args.carla_host, args.carla_port[0], args.carla_tm_port, args.carla_timeout)


def env_overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The ``[env]`` keys that ``--backend`` and the connection flags set (empty without ``--backend``)."""
    if args.backend is None:
        return {}
    _check_connection_flags(args)
    return {"backend": args.backend, "carla_host": args.carla_host, "carla_port": args.carla_port[0],
            "carla_tm_port": args.carla_tm_port, "carla_timeout": args.carla_timeout}


def _check_connection_flags(args: argparse.Namespace) -> None:
    """``--carla-tm-port`` and ``--carla-timeout`` (inf became 0 s), by the one check the CARLA connection uses."""
    from genesis_rl.sim.carla.connection import check_numbers  # imports no carla: the client is optional

    check_numbers(args.carla_port[0], args.carla_timeout, args.carla_tm_port)


def backend_from_args(args: argparse.Namespace) -> Backend:
    return make_backend(args.backend, settings_from_args(args))


# -- catalogs -------------------------------------------------------------------------------------------------
def catalog_from_json(data: Any) -> Catalog:
    """A catalog from JSON data, checked against the schema and against its backend's maps."""
    catalog = parse_catalog(data)
    scene_source(catalog.backend).check_catalog(catalog)
    return catalog


#: catalogs this process read and checked, by their file's SHA-256, newest last: each of a campaign's episodes
#: and each campaign of a benchmark reads the same catalog.json, and a 1,199-scene one takes seconds to parse and
#: check. Keyed by content, an edited file is read afresh; a Catalog is frozen.
_LOADED: OrderedDict[str, Catalog] = OrderedDict()
_LOADED_KEPT = 4


def load_catalog(path: Path | str) -> Catalog:
    """The catalog in a JSON file, checked against the schema and against its backend's maps."""
    check_size(Path(path), "catalog file", CATALOG_MB)  # read_catalog's own refusal, before the file is hashed
    digest = regular_file_sha256(path)
    if digest is not None and digest in _LOADED:
        _LOADED.move_to_end(digest)
        return _LOADED[digest]
    catalog = read_catalog(path)
    scene_source(catalog.backend).check_catalog(catalog)
    if digest is not None and regular_file_sha256(path) == digest:  # not rewritten while it was read
        _LOADED[digest] = catalog
        while len(_LOADED) > _LOADED_KEPT:
            _LOADED.popitem(last=False)
    return catalog


def catalog_or_generate(path: str | None, map_name: str, count: int, seed: int, map_field: str = "--map",
                        progress: bool = False, backend: str = "lite", traffic: str = "mixed") -> Catalog:
    """The catalog in ``path``, or else the first ``count`` scenes generated on ``map_name`` with ``seed``
    for ``backend`` (the same seed and index give the same scene whatever the count). ``map_field`` names the
    setting in the error for an unknown map. ``traffic`` other than mixed (lite's free_flow) is generated
    by lite's scene source alone."""
    if path:
        return load_catalog(path)
    cls = check_backend_setting(backend, path, "backend", "a catalog file")
    source = scene_source(cls.catalog_kind)
    source.check_map(map_name, map_field)
    if count > MAX_GENERATED_ON_THE_FLY:
        raise UserInputError(f"{count} scenes (indices up to {count - 1}) would be generated on the fly; without a "
                             f"catalog at most {MAX_GENERATED_ON_THE_FLY} are. Make a catalog once with "
                             f"'genesis-rl scenes --map {map_name} --count {count} --out FILE' and pass it as "
                             "--catalog FILE")
    if traffic != "mixed":
        if cls.catalog_kind != "lite":
            raise UserInputError(f"traffic '{traffic}' is generated on lite's maps only; backend '{backend}' "
                                 "generates mixed traffic (or pass a catalog file)")
        from genesis_rl.sim.lite.scenes import generate_catalog

        return generate_catalog(map_name, count, seed, progress=progress, traffic=traffic)
    return source.generate(map_name, count, seed, ConnectionSettings(), progress=progress)
