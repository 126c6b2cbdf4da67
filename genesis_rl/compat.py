"""Old import paths of modules that moved when the package was laid out by its data flow (0.30.0).

A plug-in, a config's ``system`` or ``rules`` path, a checkpoint's pickled class or a record written by 0.29.0
may name a module by its old path (``genesis_rl.knobs``, ``genesis_rl.system.builtin``...). Importing such a
name gives a module that forwards every attribute to the module's new home and warns once, so those files keep
working for one release; docs/extending.md lists the new paths.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from typing import Any

#: old path -> new path, both below ``genesis_rl.``; a package's submodules follow their package
MOVED: dict[str, str] = {
    "errors": "core.errors",
    "limits": "core.limits",
    "ranges": "core.ranges",
    "signals": "core.signals",
    "plugins": "core.plugins",
    "trust": "core.trust",
    "provenance": "core.provenance",
    "config": "core.config",
    "netprobe": "core.netprobe",
    "parsing": "core.parsing",
    "io_utils": "core.files.io_utils",
    "output_paths": "core.files.output_paths",
    "output_folder": "core.files.output_folder",
    "special_files": "core.files.special_files",
    "knobs": "world.knobs",
    "actor_knobs": "world.actor_knobs",
    "weather_schedule": "world.weather_schedule",
    "step_record": "world.step_record",
    "odd": "world.odd",
    "scenes": "world.scenes",
    "geometry": "sim.geometry",
    "backends": "sim.backends",
    "lite": "sim.lite",
    "carla_backend": "sim.carla",
    "scenic_scenes": "sim.scenic",
    "perception": "sut.perception",
    "system": "sut.system",
    "zoo": "sut.zoo",
    "drive": "loop.drive",
    "rules": "loop.rules",
    "viz": "loop.viz",
    "evaluation.failure_modes": "labels.failure_modes",
    "evaluation.blame": "labels.blame",
    "evaluation.careful_driver": "labels.careful_driver",
    "evaluation.distinct": "labels.distinct",
    "evaluation.actor_summary": "labels.actor_summary",
    "evaluation.campaign": "campaigns.campaign",
    "evaluation.campaign_files": "campaigns.campaign_files",
    "evaluation.campaign_folder": "campaigns.campaign_folder",
    "evaluation.campaign_spec": "campaigns.campaign_spec",
    "evaluation.episodes": "campaigns.episodes",
    "evaluation.executors": "campaigns.executors",
    "evaluation.records": "campaigns.records",
    "evaluation.summary": "campaigns.summary",
    "evaluation.worker": "campaigns.worker",
    "evaluation.stats": "core.stats",
    "evaluation.report": "analysis.report",
    "evaluation.report_natural": "analysis.report_natural",
    "evaluation.compare": "analysis.compare",
    "evaluation.reactivity": "analysis.reactivity",
    "evaluation.corners": "analysis.corners",
    "evaluation.estimate_files": "analysis.estimate_files",
    "evaluation.export": "exports.dataset",
    "openscenario": "exports.openscenario",
    "evaluation.commands": "commands.campaign_commands",
    "perception.commands": "commands.perception_commands",
    "cli": "commands.cli",
    "cli_args": "commands.cli_args",
    "entry": "commands.entry",
    "benchmark_cmd": "commands.benchmark",
    "estimate_cmd": "commands.estimate",
    "export_cmd": "commands.export",
    "harden_cmd": "commands.harden",
    "realism_cmd": "commands.realism",
    "zoo_cmd": "commands.zoo",
    "render_cmd": "commands.render",
    "drive_cmd": "commands.drive",
    "bench": "commands.speed",
    "system.route": "sim.route",
}
#: the release that stops reading the old paths
REMOVED_IN = "0.31.0"


def new_path(name: str) -> str | None:
    """The module's new dotted path if ``name`` is an old one (the longest moved prefix wins), else None."""
    if not name.startswith("genesis_rl."):
        return None
    rest = name[len("genesis_rl."):]
    best = max((old for old in MOVED if rest == old or rest.startswith(old + ".")), key=len, default=None)
    if best is None:
        return None
    return "genesis_rl." + MOVED[best] + rest[len(best):]


class _Forwarding(types.ModuleType):
    """Stands at an old path; every attribute is the new module's."""

    def __init__(self, name: str, target: types.ModuleType) -> None:
        super().__init__(name, target.__doc__)
        self.__dict__["_target"] = target
        if hasattr(target, "__path__"):
            self.__path__: list[str] = []  # so that ``old.sub`` is looked up, and found by the finder below

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.__dict__["_target"], attr)

    def __dir__(self) -> list[str]:
        return dir(self.__dict__["_target"])


class _OldPaths(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    _warned: set[str] = set()

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        new = new_path(name)
        if new is None:
            return None
        return importlib.machinery.ModuleSpec(name, self, is_package=True)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        new = new_path(spec.name)
        assert new is not None
        if spec.name not in self._warned:
            self._warned.add(spec.name)
            warnings.warn(f"{spec.name} moved to {new}; the old path is read until {REMOVED_IN}",
                          DeprecationWarning, stacklevel=3)
        return _Forwarding(spec.name, importlib.import_module(new))

    def exec_module(self, module: types.ModuleType) -> None:
        return None


def install() -> None:
    """Put the old-path finder on ``sys.meta_path`` once (``import genesis_rl`` does)."""
    if not any(isinstance(f, _OldPaths) for f in sys.meta_path):
        sys.meta_path.append(_OldPaths())
