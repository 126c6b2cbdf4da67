"""The catalog's ``lane`` field on CARLA maps: one int for an OpenDRIVE (road id, lane id) pair.

Shared by the scene generator (which writes it) and the spawner (which reads it back), so neither imports
the other.
"""

from __future__ import annotations

_LANE_OFFSET = 50  # lane ids are small (|id| < 50): key = road_id * 100 + lane_id + 50


def lane_key(road_id: int, lane_id: int) -> int:
    """One int for an OpenDRIVE (road, lane) pair, as the catalog's ``lane`` field holds."""
    if not -_LANE_OFFSET < lane_id < _LANE_OFFSET:
        raise ValueError(f"lane id {lane_id} out of range")
    return int(road_id) * 2 * _LANE_OFFSET + int(lane_id) + _LANE_OFFSET


def lane_from_key(key: int) -> tuple[int, int]:
    """(road id, lane id) of a catalog ``lane`` written by this generator."""
    road, rest = divmod(int(key), 2 * _LANE_OFFSET)
    return road, rest - _LANE_OFFSET
