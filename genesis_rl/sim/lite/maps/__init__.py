"""Maps of the lite backend: a lane graph (for traffic) plus scenery (for the renderer)."""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.lite.maps.highway import build_highway
from genesis_rl.sim.lite.maps.lane_graph import RoadMap
from genesis_rl.sim.lite.maps.urban import build_urban

_BUILDERS: dict[str, Callable[[], RoadMap]] = {"urban": build_urban, "highway": build_highway}
MAP_NAMES = tuple(_BUILDERS)


@lru_cache(maxsize=4)
def load_map(name: str) -> RoadMap:
    """Build (once per process) and return the named map. Maps are deterministic: no seed."""
    if name not in _BUILDERS:
        raise UserInputError(f"unknown map '{name}'; allowed: {', '.join(MAP_NAMES)}")
    return _BUILDERS[name]()
