"""Deep copies of an episode's state that share what never changes within it (a detector's network, a map).

An exact snapshot must copy every mutable part of a simulation and of the system under test (traffic, trackers,
queues, random generators); copying a neural network's weights at every snapshot would cost far more than the
state itself and buys nothing, since inference does not change them. ``copy_state`` finds those parts (torch
modules, and objects whose class says ``SNAPSHOT_SHARED = True``) and lets the copy point at the originals.
"""

from __future__ import annotations

import copy
import sys
from collections.abc import Iterable
from typing import Any, TypeVar

T = TypeVar("T")

#: how deep ``shared_parts`` looks for shared parts inside an object's attributes and containers
_DEPTH = 6


def _is_shared(x: object) -> bool:
    if getattr(type(x), "SNAPSHOT_SHARED", False):
        return True
    torch = sys.modules.get("torch")  # never imported here: a system without torch has no module to share
    return torch is not None and isinstance(x, torch.nn.Module)


def shared_parts(obj: object, depth: int = _DEPTH) -> list[object]:
    """The parts of ``obj`` (itself included) that a state copy shares rather than copies."""
    found: list[object] = []
    seen: set[int] = set()

    def walk(x: object, left: int) -> None:
        if id(x) in seen or left < 0 or isinstance(x, (str, bytes, int, float, bool, type(None))):
            return
        seen.add(id(x))
        if _is_shared(x):
            found.append(x)
            return
        if isinstance(x, dict):
            children: Iterable[object] = x.values()
        elif isinstance(x, (list, tuple, set, frozenset)):
            children = x
        elif hasattr(x, "__dict__"):
            children = vars(x).values()
        else:
            return
        for child in children:
            walk(child, left - 1)

    walk(obj, depth)
    return found


def copy_state(obj: T, shared: Iterable[object] = ()) -> T:
    """A deep copy of ``obj`` that shares ``shared`` and every part ``shared_parts`` finds in it."""
    memo: dict[int, Any] = {}
    for part in (*shared, *shared_parts(obj)):
        memo[id(part)] = part
    return copy.deepcopy(obj, memo)
