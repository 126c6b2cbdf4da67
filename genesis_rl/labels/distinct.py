"""Distinct failures: 34 collisions in the same dense fog are one finding, not 34.

Two failures are *the same* when they agree on every part of :func:`failure_key`: the failure mode (what the
detector did), the blame (perception, control, unavoidable), the ODD status at the impact, the conditions at
the impact in bands (visibility, rain category, light, road state) and what was hit (the lead, braking or
not, or another vehicle). The bands are the ones an ODD is written in, so a cluster is a statement a safety
engineer can check: "non-detection of a braking lead in 50-150 m fog by day on a dry road, a perception
failure inside the domain". Each cluster keeps one representative: its most natural failure (the highest
log-likelihood of the weather up to the impact), the one to show first (VerifAI's error table; ADFuzz counts
only distinct violations).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from genesis_rl.labels.careful_driver import ACTOR_EVENT_WINDOW_S
from genesis_rl.sim.interface import ActorEvent
from genesis_rl.world.odd.domain import IN_ODD
from genesis_rl.world.step_record import StepRecord

#: visibility bands [m]: fog warnings (< 50), dense fog to mist (50-150), haze (150-500), clear
VISIBILITY_BANDS = ((50.0, "<50 m"), (150.0, "50-150 m"), (500.0, "150-500 m"), (float("inf"), ">=500 m"))
#: rain rate categories [mm/h] (AMS glossary)
RAIN_BANDS = ((0.0, "no rain"), (2.5, "light rain"), (7.6, "moderate rain"), (50.0, "heavy rain"),
              (float("inf"), "violent rain"))
#: the lead "brakes" when its speed fell by at least this much [m/s] in LEAD_BRAKING_S before the impact
LEAD_BRAKING_DROP = 3.0
LEAD_BRAKING_S = 3.0
KEY_FIELDS = ("mode", "blame", "odd_status", "visibility", "rain", "light", "road_state", "hit")


def visibility_band(visibility_m: float) -> str:
    return next(name for upper, name in VISIBILITY_BANDS if visibility_m < upper)


def rain_band(rain_mm_h: float) -> str:
    if rain_mm_h <= 0.0:
        return RAIN_BANDS[0][1]
    return next(name for upper, name in RAIN_BANDS[1:] if rain_mm_h < upper)


def what_was_hit(records: Sequence[StepRecord], hit_at: int, dt: float = 0.05,
                 actor_events: Sequence[ActorEvent] | None = None) -> str:
    """``cut in by the tester`` (the ``cut_in_ttc`` knob made the vehicle hit cut in within the last
    ``ACTOR_EVENT_WINDOW_S``), ``lead braked by the tester`` (the ``lead_decel`` knob braked the vehicle hit: with
    the episode's ``actor_events``, an event with that vehicle in the window; without them, for campaigns
    before 0.15, the knob was on in the window), ``braking lead``, ``lead`` or ``other vehicle`` (the hit
    vehicle was not the lead just before)."""
    vid = records[hit_at].collision.other_id
    t_hit = records[hit_at].time_s

    def acted(kind: str, window_s: float) -> bool:
        return any(e.kind == kind and e.vehicle_id == vid and t_hit - window_s <= e.onset_s <= t_hit
                   for e in actor_events or ())

    if acted("cut_in", ACTOR_EVENT_WINDOW_S):
        return "cut in by the tester"
    before = records[max(0, hit_at - 1)]
    if before.lead.vehicle_id != vid:
        return "other vehicle"
    back = max(0, hit_at - int(round(LEAD_BRAKING_S / dt)))
    braked = acted("lead_braking", ACTOR_EVENT_WINDOW_S) if actor_events is not None else \
        any(r.knobs.get("lead_decel", 0.0) > 0.0 for r in records[back:hit_at + 1])
    if braked:
        return "lead braked by the tester"
    speeds = [r.lead.speed for r in records[back:hit_at + 1] if r.lead.vehicle_id == vid and np.isfinite(r.lead.speed)]
    return "braking lead" if speeds and max(speeds) - speeds[-1] >= LEAD_BRAKING_DROP else "lead"


def failure_key(failure: Mapping[str, Any]) -> tuple[str, ...]:
    """The tuple of KEY_FIELDS that decides whether two failures are the same."""
    return tuple(str(failure.get(k)) for k in KEY_FIELDS)


def _most_natural_first(failure: Mapping[str, Any]) -> tuple[float, int]:
    natural = failure.get("naturalness")
    return (-float(natural) if natural is not None else np.inf, int(failure.get("scene", 0)))


def clusters(failures: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Failures grouped by :func:`failure_key`: each cluster with its key fields, its count, and its members
    ordered most natural first (the first is the representative). Largest clusters first."""
    groups: dict[tuple[str, ...], list[Mapping[str, Any]]] = {}
    for f in failures:
        groups.setdefault(failure_key(f), []).append(f)
    out: list[dict[str, Any]] = []
    for key, members in sorted(groups.items(), key=lambda kv: (-len(kv[1]), kv[0])):
        out.append({**dict(zip(KEY_FIELDS, key, strict=True)), "count": len(members),
                    "members": sorted(members, key=_most_natural_first)})
    return out


def failure_of(row: Mapping[str, Any], policy: str) -> dict[str, Any]:
    f = dict(row["failure"])
    f.update(policy=policy, scene=row["scene"], episode_seed=row["episode_seed"], record=row.get("record"))
    return f


def _blame_counts(failures: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    return {b: sum(1 for f in failures if f.get("blame") == b) for b in ("perception", "control", "unavoidable")}


def natural_summary(policy: str, rows: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """A policy's natural-edge-case figures (None for a campaign older than 0.6.0): its collisions inside the
    ODD with an exact CI on their rate, the distinct ones, the blame split, naturalness, and the ODD share
    of its steps; the clusters with their members (most natural first)."""
    from genesis_rl.core.stats import clopper_pearson

    if not rows or "naturalness" not in rows[0]:
        return None
    failures = [failure_of(r, policy) for r in rows if r.get("failure")]
    has_odd = any("odd" in r for r in rows)
    in_odd = [f for f in failures if f.get("odd_status") in IN_ODD] if has_odd else failures
    steps = {s: sum(r.get("odd", {}).get(s, 0) for r in rows) for s in ("inside", "boundary", "outside")}
    total_steps = sum(steps.values())
    groups = clusters(in_odd)
    avoidable = [f for f in in_odd if f.get("blame") != "unavoidable"]
    return {
        "odd": has_odd,
        "collisions": len(failures),
        "in_odd_collisions": len(in_odd),
        "in_odd_collision_rate": clopper_pearson(len(in_odd), len(rows)),
        "distinct_in_odd_failures": len(groups),
        # the system's own failures: an unavoidable collision (the reference collides too) is not one
        "avoidable_in_odd_collisions": len(avoidable),
        "distinct_avoidable_in_odd_failures": sum(1 for c in groups if c["blame"] != "unavoidable"),
        "references": {ref: sum(1 for f in in_odd if f.get("reference") == ref)
                       for ref in sorted({str(f["reference"]) for f in in_odd if f.get("reference")})},
        "blame": _blame_counts(in_odd),
        "outside_odd_blame": _blame_counts([f for f in failures if f not in in_odd]),
        "naturalness_mean": round(float(np.mean([r["naturalness"]["ratio_to_held"] for r in rows])), 3),
        "failure_naturalness_mean": round(float(np.mean([f["naturalness"] for f in in_odd])), 3) if in_odd else None,
        "odd_steps": {s: round(n / total_steps, 4) for s, n in steps.items()} if has_odd and total_steps else None,
        "clusters": [{**{k: c[k] for k in (*KEY_FIELDS, "count")},
                      "reference": c["members"][0].get("reference"),
                      "members": [{k: m.get(k) for k in ("scene", "episode_seed", "naturalness", "record", "step")}
                                  for m in c["members"]]} for c in groups],
    }
