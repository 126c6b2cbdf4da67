"""Maps of the lite backend: a lane graph (for traffic) plus scenery (for the renderer)."""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

from genesis_rl.errors import UserInputError
from genesis_rl.lite.maps.lane_graph import RoadMap


def _builders() -> dict[str, Callable[[], RoadMap]]:
    from genesis_rl.lite.maps.highway import build_highway
    from genesis_rl.lite.maps.urban import build_urban

    return {"urban": build_urban, "highway": build_highway}


MAP_NAMES = ("urban", "highway")


@lru_cache(maxsize=4)
def load_map(name: str) -> RoadMap:
    """Build (once per process) and return the named map. Maps are deterministic: no seed."""
    builders = _builders()
    if name not in builders:
        raise UserInputError(f"unknown map '{name}'; allowed: {', '.join(MAP_NAMES)}")
    return builders[name]()
