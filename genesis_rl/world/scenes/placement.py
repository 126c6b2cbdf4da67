"""Placing catalog vehicles, the same on every backend: seeded NPC driving styles, makes by weight, and the
overlap test between padded vehicle boxes. Backend-neutral, so the CARLA generator does not import lite."""

from __future__ import annotations

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


def boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two convex quads (4x2 corners) overlap (touching counts as no overlap)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        axes = np.column_stack([-edges[:, 1], edges[:, 0]])
        pa, pb = a @ axes.T, b @ axes.T
        if np.any((pa.max(0) <= pb.min(0)) | (pb.max(0) <= pa.min(0))):
            return False
    return True


#: the traffic a scene generator places: ``mixed`` (the paper's: the lead stops now and then, others crawl
#: or cruise) or ``free_flow`` (everyone cruises near the limit and nobody stops on its own, so only an actor
#: knob brakes the lead: the scenes a timing weakness is measured on, docs/zoo.md)
TRAFFIC = ("mixed", "free_flow")


def draw_autopilot(rng: np.random.Generator, limit: float, role: str, traffic: str = "mixed") -> dict[str, float]:
    """An NPC's seeded driving style (lite's AutopilotParams; CARLA's traffic manager reads target_speed
    and min_gap), around the lane's speed ``limit`` [m/s]. Under ``free_flow`` no one stops on its own and
    the lead cruises a little under the limit, so that a faster ego catches up and follows it."""
    if traffic == "free_flow":
        return {
            "target_speed": float(limit * (rng.uniform(0.85, 0.95) if role == "lead" else rng.uniform(0.85, 1.05))),
            "time_gap": float(rng.uniform(1.0, 2.0)),
            "min_gap": float(rng.uniform(1.5, 3.0)),
            "max_accel": float(rng.uniform(1.2, 2.5)),
            "comfort_decel": float(rng.uniform(2.0, 3.5)),
            "stop_rate": 0.0,
            "speed_noise": float(rng.uniform(0.05, 0.2)),
        }
    return {
        "target_speed": float(limit * rng.uniform(0.75, 1.05)),
        "time_gap": float(rng.uniform(1.0, 2.0)),
        "min_gap": float(rng.uniform(1.5, 3.0)),
        "max_accel": float(rng.uniform(1.2, 2.5)),
        "comfort_decel": float(rng.uniform(2.0, 3.5)),
        # the lead brakes to a stop now and then so the ego must react
        "stop_rate": float(rng.uniform(1.5, 3.0) if role == "lead" else rng.uniform(0.0, 0.5)),
        "speed_noise": float(rng.uniform(0.1, 0.4)),
    }


@functools.cache
def _make_odds() -> tuple[list[str], np.ndarray]:
    """The makes and their probabilities (the makes are fixed; scene generation draws one per vehicle tried)."""
    names = list(MAKES)
    w = np.array([MAKES[n].weight for n in names])
    return names, w / w.sum()


def draw_make(rng: np.random.Generator) -> str:
    """A vehicle make, drawn by the makes' weights."""
    names, p = _make_odds()
    return str(names[int(rng.choice(len(names), p=p))])


def fits(spec: VehicleSpec, placed: list[VehicleSpec], search_radius: float = 15.0) -> bool:
    """No overlap with the ``placed`` vehicles within ``search_radius`` metres, with a 1 m margin front and
    back and 0.2 m at the sides."""
    m = MAKES[spec.make]
    r = 0.5 * math.hypot(m.length + 2.0, m.width + 0.4)  # the padded box's bounding circle
    a: np.ndarray | None = None
    for other in placed:
        d2 = (other.x - spec.x) ** 2 + (other.y - spec.y) ** 2
        mo = MAKES[other.make]
        ro = 0.5 * math.hypot(mo.length + 2.0, mo.width + 0.4)
        if d2 > search_radius**2 or d2 > (r + ro + 1e-6) ** 2:  # apart: the boxes cannot overlap, no SAT needed
            continue
        if a is None:
            a = box_corners(spec.x, spec.y, spec.yaw, m.length + 2.0, m.width + 0.4)
        if boxes_overlap(a, box_corners(other.x, other.y, other.yaw, mo.length + 2.0, mo.width + 0.4)):
            return False
    return True
