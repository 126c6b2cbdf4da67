"""What the actor knobs made happen in a policy's episodes (issue 32): how many cut-ins, how short, how fast.

A cut-in's time-to-collision is R157's measure, taken when it became perceivable (``perceived_ttc_s``, 0.25 on);
episodes written before 0.25 have only the onset's (``ttc_s``), which is counted instead and said so
(``measured_at``). R157's boundary: the shortest time-to-collision a careful driver handles is 1.64 s at its
largest relative speed (60 km/h), so a cut-in at or under it is one the regulation's own driver may not
handle."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

#: UN R157's longest boundary time-to-collision [s] (at 60 km/h of relative speed)
R157_BOUNDARY_TTC_S = 1.64
#: a cut-in at or under this time-to-collision [s] is a short one (docs/results.md sections 10 and 11)
SHORT_CUT_IN_TTC_S = 4.0


def _ttc(event: dict[str, Any]) -> tuple[float, bool]:
    """The cut-in's time-to-collision [s] and whether it was taken where R157 takes it."""
    seen = event.get("perceived_ttc_s")
    if seen is not None:
        return float(seen), True
    onset = event.get("ttc_s")
    return (math.inf if onset is None else float(onset)), False


def cut_in_summary(episodes: Iterable[dict[str, Any]]) -> dict[str, Any] | None:
    """Cut-ins over a policy's episode rows (None: no cut-in happened): count, episodes with one, how many
    were short or at R157's boundary, the shortest and median time-to-collision, the largest closing speed,
    and where the time-to-collision was measured (``perceivable``, ``onset`` or ``both``)."""
    ttcs: list[float] = []
    closing: list[float] = []
    where: set[str] = set()
    scenes = 0
    for ep in episodes:
        cuts = [e for e in ep.get("actor_events") or [] if e.get("kind") == "cut_in"]
        scenes += bool(cuts)
        for e in cuts:
            t, seen = _ttc(e)
            ttcs.append(t)
            where.add("perceivable" if seen else "onset")
            if e.get("closing_m_s") is not None:
                closing.append(float(e["closing_m_s"]))
    if not ttcs:
        return None
    finite = sorted(t for t in ttcs if math.isfinite(t))
    return {"cut_ins": len(ttcs), "episodes": scenes,
            "under_4s": sum(t <= SHORT_CUT_IN_TTC_S for t in ttcs),
            "at_r157_boundary": sum(t <= R157_BOUNDARY_TTC_S for t in ttcs),
            "shortest_ttc_s": round(finite[0], 3) if finite else None,
            "median_ttc_s": round(finite[len(finite) // 2], 3) if finite else None,
            "largest_closing_m_s": round(max(closing), 3) if closing else None,
            "measured_at": where.pop() if len(where) == 1 else "both"}


def cut_in_markdown(policies: dict[str, dict[str, Any]]) -> list[str]:
    """The cut-in table of a summary's policies (no lines when no policy made a cut-in)."""
    rows = [(p, s["cut_ins"]) for p, s in policies.items() if s.get("cut_ins")]
    if not rows:
        return []
    lines = ["", f"| policy | cut-ins (episodes) | under {SHORT_CUT_IN_TTC_S:g} s | at R157's {R157_BOUNDARY_TTC_S} s "
             "or under | shortest / median time-to-collision | largest closing speed | measured at |",
             "|" + " --- |" * 7]
    for p, c in rows:
        short = "–" if c["shortest_ttc_s"] is None else f"{c['shortest_ttc_s']:.2f} / {c['median_ttc_s']:.2f} s"
        fast = "–" if c["largest_closing_m_s"] is None else f"{c['largest_closing_m_s']:.1f} m/s"
        lines.append(f"| {p} | {c['cut_ins']} ({c['episodes']}) | {c['under_4s']} | {c['at_r157_boundary']} | "
                     f"{short} | {fast} | {c['measured_at']} |")
    return lines


def cut_in_html(policies: dict[str, dict[str, Any]]) -> list[str]:
    """The cut-in table as the report's HTML (nothing when no policy made a cut-in)."""
    lines = cut_in_markdown(policies)
    if not lines:
        return []
    head, _, *body = lines[1:]
    cells = [[c.strip() for c in row.strip("|").split("|")] for row in (head, *body)]
    out = ["<h2>Cut-ins the tester asked for</h2><p class=meta>time-to-collision as UN R157 takes it, once the "
           "cutter has wandered 0.375 m toward the ego's lane (campaigns before 0.25: at the lane change's onset); "
           f"R157's careful driver handles down to {R157_BOUNDARY_TTC_S} s at 60 km/h of relative speed</p><table>",
           "<tr>" + "".join(f"<th{' class=l' if i == 0 else ''}>{c}</th>" for i, c in enumerate(cells[0])) + "</tr>"]
    out += ["<tr>" + "".join(f"<td{' class=l' if i == 0 else ''}>{c}</td>" for i, c in enumerate(r)) + "</tr>"
            for r in cells[1:]]
    return [*out, "</table>"]


#: UN R157 Annex 4 Appendix 3: relative speed [km/h] -> the shortest cut-in time-to-collision [s] a careful
#: driver handles
R157_BOUNDARY = ((10.0, 0.48), (20.0, 0.71), (30.0, 0.94), (40.0, 1.18), (50.0, 1.41), (60.0, 1.64))


def cut_in_points(episodes: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every cut-in of a policy's episodes: closing speed [km/h], time-to-collision [s] (as ``_ttc``), and the
    blame when the ego then hit that car (None: it did not)."""
    out = []
    for ep in episodes:
        failure = ep.get("failure") or {}
        for e in ep.get("actor_events") or []:
            if e.get("kind") != "cut_in" or e.get("closing_m_s") is None:
                continue
            ttc, seen = _ttc(e)
            hit = failure.get("vehicle_id") == e.get("vehicle_id") and failure.get("hit") == "cut in by the tester"
            out.append({"closing_km_h": 3.6 * float(e["closing_m_s"]), "ttc_s": ttc, "perceived": seen,
                        "scene": ep.get("scene"), "blame": failure.get("blame") if hit else None})
    return out


def fig_cut_ins(rows: dict[str, list[dict[str, Any]]], colors: dict[str, str]) -> Any | None:
    """Each policy's cut-ins against R157's boundary (None: no cut-in): closing speed across, time-to-collision
    up, a cross where the ego hit the car (red: avoidable, grey: unavoidable for the careful driver)."""
    points = {p: cut_in_points(eps) for p, eps in rows.items()}
    if not any(points.values()):
        return None
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    speeds, ttcs = zip(*R157_BOUNDARY, strict=True)
    ax.fill_between(speeds, 0, ttcs, color="#f5b7b1", alpha=0.5, lw=0, label="beyond R157's careful driver")
    ax.plot(speeds, ttcs, color="#c0392b", lw=1.2)
    for p, pts in points.items():
        if not pts:
            continue
        ax.scatter([q["closing_km_h"] for q in pts], [min(q["ttc_s"], 10.0) for q in pts], s=18, alpha=0.75,
                   color=colors.get(p, "#333333"), label=f"{p} ({len(pts)})")
        for q in pts:
            if q["blame"] is not None:
                ax.scatter([q["closing_km_h"]], [min(q["ttc_s"], 10.0)], marker="x", s=70, linewidths=2,
                           color="#7f8c8d" if q["blame"] == "unavoidable" else "#c0392b")
    ax.scatter([], [], marker="x", color="#c0392b", label="hit: avoidable")
    ax.scatter([], [], marker="x", color="#7f8c8d", label="hit: unavoidable")
    ax.set_xlabel("closing speed at the cut-in [km/h]")
    ax.set_ylabel("time-to-collision [s]")
    ax.set_ylim(0, 10.3)
    ax.set_xlim(0, max(65.0, max(q["closing_km_h"] for pts in points.values() for q in pts) + 5))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="center right")
    fig.tight_layout()
    return fig
