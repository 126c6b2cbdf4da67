"""Placing catalog vehicles, the same on every backend: seeded NPC driving styles, makes by weight, and the
overlap test between padded vehicle boxes. Backend-neutral, so the CARLA generator does not import lite."""

from __future__ import annotations

import bisect
import functools
import math

import numpy as np

from genesis_rl.world.scenes.catalog import VehicleSpec
from genesis_rl.world.scenes.vehicles import MAKES


def box_corners(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = length / 2, width / 2
    local = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    return local @ np.array([[c, s], [-s, c]]) + np.array([x, y])


_NEXT_CORNER = [1, 2, 3, 0]
_TURN = np.array([-1.0, 1.0])


def edge_normals(poly: np.ndarray) -> np.ndarray:
    """The separating-axis candidates of a convex quad: its edges turned by 90 degrees (4x2)."""
    edges = poly[_NEXT_CORNER] - poly
    return edges[:, ::-1] * _TURN  # (-ey, ex): exact, as negating and copying are


def _overlap(a: np.ndarray, axes_a: np.ndarray, b: np.ndarray, axes_b: np.ndarray) -> bool:
    for axes in (axes_a, axes_b):
        pa, pb = a @ axes.T, b @ axes.T
        if np.any((pa.max(0) <= pb.min(0)) | (pb.max(0) <= pa.min(0))):
            return False
    return True


def boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two convex quads (4x2 corners) overlap (touching counts as no overlap)."""
    return _overlap(a, edge_normals(a), b, edge_normals(b))


#: the traffic a scene generator places: ``mixed`` (the paper's: the lead stops now and then, others crawl
#: or cruise) or ``free_flow`` (everyone cruises near the limit and nobody stops on its own, so only an actor
#: knob brakes the lead: the scenes a timing weakness is measured on, docs/zoo.md)
TRAFFIC = ("mixed", "free_flow")


#: the ranges an NPC's driving style is drawn from, in the order of the draws: target speed (a fraction of the
#: lane's limit), time gap [s], minimum gap [m], acceleration, comfortable deceleration [m/s^2], the rate it stops
#: on its own (mixed traffic only) and its speed noise; by (traffic, whether it is the lead)
_STYLE_RANGES: dict[tuple[str, bool], tuple[tuple[float, float], ...]] = {
    ("free_flow", True): ((0.85, 0.95), (1.0, 2.0), (1.5, 3.0), (1.2, 2.5), (2.0, 3.5), (0.05, 0.2)),
    ("free_flow", False): ((0.85, 1.05), (1.0, 2.0), (1.5, 3.0), (1.2, 2.5), (2.0, 3.5), (0.05, 0.2)),
    # the lead brakes to a stop now and then so the ego must react
    ("mixed", True): ((0.75, 1.05), (1.0, 2.0), (1.5, 3.0), (1.2, 2.5), (2.0, 3.5), (1.5, 3.0), (0.1, 0.4)),
    ("mixed", False): ((0.75, 1.05), (1.0, 2.0), (1.5, 3.0), (1.2, 2.5), (2.0, 3.5), (0.0, 0.5), (0.1, 0.4)),
}
#: each range's low end and width, as numpy's ``Generator.uniform`` computes them
_STYLE_BOUNDS = {key: (np.array([lo for lo, _ in r]), np.array([hi for _, hi in r]) - np.array([lo for lo, _ in r]))
                 for key, r in _STYLE_RANGES.items()}


def draw_autopilot(rng: np.random.Generator, limit: float, role: str, traffic: str = "mixed") -> dict[str, float]:
    """An NPC's seeded driving style (lite's AutopilotParams; CARLA's traffic manager reads target_speed
    and min_gap), around the lane's speed ``limit`` [m/s]. Under ``free_flow`` no one stops on its own and
    the lead cruises a little under the limit, so that a faster ego catches up and follows it. One draw of
    all the uniforms, ``low + width * u`` as ``rng.uniform`` computes each: the same numbers, in the same order,
    as one ``rng.uniform`` call each, at a quarter of the cost."""
    free = traffic == "free_flow"
    low, width = _STYLE_BOUNDS[("free_flow" if free else "mixed", role == "lead")]
    u = (low + width * rng.random(len(low))).tolist()
    return {
        "target_speed": float(limit * u[0]),
        "time_gap": u[1],
        "min_gap": u[2],
        "max_accel": u[3],
        "comfort_decel": u[4],
        "stop_rate": 0.0 if free else u[5],
        "speed_noise": u[-1],
    }


@functools.cache
def _make_cdf() -> tuple[list[str], list[float]]:
    """The makes and their cumulative probabilities, normalised as numpy's ``Generator.choice(p=...)`` does."""
    names = list(MAKES)
    w = np.array([MAKES[n].weight for n in names])
    cdf = (w / w.sum()).cumsum()
    cdf /= cdf[-1]
    return names, cdf.tolist()


def draw_make(rng: np.random.Generator) -> str:
    """A vehicle make, drawn by the makes' weights: ``rng.choice(makes, p=weights)``'s draw (one uniform, looked
    up in the cumulative weights), without its checks of ``p`` on each of the thousands of draws a catalog makes."""
    names, cdf = _make_cdf()
    return names[bisect.bisect_right(cdf, rng.random())]


@functools.cache
def _padded_radius(make: str) -> float:
    """The radius of the circle around a make's padded box (1 m front and back, 0.2 m at the sides)."""
    m = MAKES[make]
    return 0.5 * math.hypot(m.length + 2.0, m.width + 0.4)


@functools.lru_cache(maxsize=8192)
def _padded_box(x: float, y: float, yaw: float, make: str) -> tuple[np.ndarray, np.ndarray]:
    """A vehicle's padded box and its edge normals; a catalog tests each placed vehicle against dozens of
    candidates."""
    m = MAKES[make]
    corners = box_corners(x, y, yaw, m.length + 2.0, m.width + 0.4)
    return corners, edge_normals(corners)


def fits(spec: VehicleSpec, placed: list[VehicleSpec], search_radius: float = 15.0) -> bool:
    """No overlap with the ``placed`` vehicles within ``search_radius`` metres, with a 1 m margin front and
    back and 0.2 m at the sides."""
    r = _padded_radius(spec.make)
    mine: tuple[np.ndarray, np.ndarray] | None = None
    for other in placed:
        d2 = (other.x - spec.x) ** 2 + (other.y - spec.y) ** 2
        if d2 > search_radius**2 or d2 > (r + _padded_radius(other.make) + 1e-6) ** 2:
            continue  # apart: the boxes cannot overlap, no SAT needed
        theirs = _padded_box(other.x, other.y, other.yaw, other.make)
        if mine is None:
            mine = _padded_box(spec.x, spec.y, spec.yaw, spec.make)
        if _overlap(mine[0], mine[1], theirs[0], theirs[1]):
            return False
    return True
