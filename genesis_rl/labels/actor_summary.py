"""What the actor knobs made happen in a policy's episodes: how many cut-ins, how short, how fast.

A cut-in's time-to-collision is R157's measure, taken when it became perceivable (``perceived_ttc_s``, 0.25 on;
a cut-in that never became perceivable has none); campaigns written before 0.25 have only the onset's
(``ttc_s``), which is counted instead and said so (``measured_at``). R157's boundary: the shortest
time-to-collision a careful driver handles at each relative speed (0.48 s at 10 km/h to 1.64 s at 60 km/h); a
cut-in beyond it is one the regulation does not ask a system to handle."""

from __future__ import annotations

import html
import math
from collections.abc import Iterable
from typing import Any

import numpy as np

#: UN R157's longest boundary time-to-collision [s] (at 60 km/h of relative speed)
R157_BOUNDARY_TTC_S = 1.64
#: a cut-in at or under this time-to-collision [s] is a short one (docs/results/10-other-road-users-blame.md and 11)
SHORT_CUT_IN_TTC_S = 4.0
#: UN R157 Annex 4 Appendix 3: relative speed [km/h] -> the shortest cut-in time-to-collision [s] a careful
#: driver handles
R157_BOUNDARY = ((10.0, 0.48), (20.0, 0.71), (30.0, 0.94), (40.0, 1.18), (50.0, 1.41), (60.0, 1.64))


def r157_boundary_ttc(closing_km_h: float) -> float:
    """R157's shortest cut-in time-to-collision [s] a careful driver handles at this relative speed [km/h]
    (linear between the regulation's points, held beyond its ends)."""
    speeds, ttcs = zip(*R157_BOUNDARY, strict=True)
    return float(np.interp(closing_km_h, speeds, ttcs))


def measured_at_perceivable(episodes: Iterable[dict[str, Any]]) -> bool:
    """Whether these episodes took a cut-in's time-to-collision at the perceivable moment (0.25 on: every
    cut-in event has ``perceived_ttc_s``, null where unknown; 0.25.0's first campaigns wrote it only when the
    gap was closing then) or at the onset (before 0.25)."""
    return any("perceived_ttc_s" in e for ep in episodes for e in ep.get("actor_events") or [])


def _ttc(event: dict[str, Any], at_perceivable: bool) -> float | None:
    """The cut-in's time-to-collision [s]: R157's, once perceivable (inf when the gap was not closing then;
    None: it never became perceivable), or the onset's for episodes written before 0.25."""
    if not at_perceivable:
        return math.inf if event.get("ttc_s") is None else float(event["ttc_s"])
    if event.get("perceivable_s") is None:
        return None
    seen = event.get("perceived_ttc_s")
    return math.inf if seen is None else float(seen)


def cut_in_summary(episodes: Iterable[dict[str, Any]]) -> dict[str, Any] | None:
    """Cut-ins over a policy's episode rows (None: no cut-in happened): count, episodes with one, how many
    never became perceivable (the cutter never wandered 0.375 m toward the ego: no time-to-collision), how
    many were short, at R157's 1.64 s or under, or beyond R157's boundary at their closing speed, the shortest
    and median time-to-collision, the largest closing speed, and where it was measured."""
    episodes = list(episodes)
    at_perceivable = measured_at_perceivable(episodes)
    ttcs: list[float] = []
    beyond = never = cut_ins = scenes = 0
    closing: list[float] = []
    for ep in episodes:
        cuts = [e for e in ep.get("actor_events") or [] if e.get("kind") == "cut_in"]
        scenes += bool(cuts)
        for e in cuts:
            cut_ins += 1
            if e.get("closing_m_s") is not None:
                closing.append(float(e["closing_m_s"]))
            t = _ttc(e, at_perceivable)
            if t is None:
                never += 1
                continue
            ttcs.append(t)
            if e.get("closing_m_s") is not None and t < r157_boundary_ttc(3.6 * float(e["closing_m_s"])):
                beyond += 1
    if not cut_ins:
        return None
    finite = sorted(t for t in ttcs if math.isfinite(t))
    return {"cut_ins": cut_ins, "episodes": scenes, "never_perceivable": never if at_perceivable else None,
            "under_4s": sum(t <= SHORT_CUT_IN_TTC_S for t in ttcs),
            "at_r157_boundary": sum(t <= R157_BOUNDARY_TTC_S for t in ttcs), "beyond_r157": beyond,
            "shortest_ttc_s": round(finite[0], 3) if finite else None,
            "median_ttc_s": round(finite[len(finite) // 2], 3) if finite else None,
            "largest_closing_m_s": round(max(closing), 3) if closing else None,
            "measured_at": "perceivable" if at_perceivable else "onset"}


def _table(policies: dict[str, dict[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """The cut-in table's header and one row of cells per policy that made a cut-in (no rows: none did)."""
    head = ["policy", "cut-ins (episodes)", "never perceivable", f"under {SHORT_CUT_IN_TTC_S:g} s",
            f"at {R157_BOUNDARY_TTC_S} s or under", "beyond R157's boundary", "shortest / median time-to-collision",
            "largest closing speed", "measured at"]
    rows = []
    for p, c in ((p, s["cut_ins"]) for p, s in policies.items() if s.get("cut_ins")):
        short = "–" if c["shortest_ttc_s"] is None else f"{c['shortest_ttc_s']:.2f} / {c['median_ttc_s']:.2f} s"
        fast = "–" if c["largest_closing_m_s"] is None else f"{c['largest_closing_m_s']:.1f} m/s"
        never = "–" if c.get("never_perceivable") is None else str(c["never_perceivable"])
        rows.append([p, f"{c['cut_ins']} ({c['episodes']})", never, str(c["under_4s"]), str(c["at_r157_boundary"]),
                     str(c.get("beyond_r157", "–")), short, fast, c["measured_at"]])
    return head, rows


def cut_in_markdown(policies: dict[str, dict[str, Any]]) -> list[str]:
    """The cut-in table of a summary's policies (no lines when no policy made a cut-in)."""
    head, rows = _table(policies)
    if not rows:
        return []
    return ["", "| " + " | ".join(head) + " |", "|" + " --- |" * len(head),
            *("| " + " | ".join(r) + " |" for r in rows)]


def cut_in_html(policies: dict[str, dict[str, Any]]) -> list[str]:
    """The cut-in table as the report's HTML (nothing when no policy made a cut-in)."""
    head, rows = _table(policies)
    if not rows:
        return []

    def cells(tag: str, row: list[str]) -> str:
        return "<tr>" + "".join(f"<{tag}{' class=l' if i == 0 else ''}>{html.escape(c)}</{tag}>"
                                for i, c in enumerate(row)) + "</tr>"

    return ["<h2>Cut-ins the tester asked for</h2><p class=meta>time-to-collision as UN R157 takes it, once the "
            "cutter has wandered 0.375 m toward the ego's lane (campaigns before 0.25: at the lane change's onset); "
            f"R157's careful driver handles down to {R157_BOUNDARY_TTC_S} s at 60 km/h of relative speed</p><table>",
            cells("th", head), *(cells("td", r) for r in rows), "</table>"]


def cut_in_points(episodes: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every cut-in of a policy's episodes with a time-to-collision (``_ttc``): closing speed [km/h],
    time-to-collision [s], and the blame when the ego then hit that car (None: it did not)."""
    episodes = list(episodes)
    at_perceivable = measured_at_perceivable(episodes)
    out = []
    for ep in episodes:
        failure = ep.get("failure") or {}
        for e in ep.get("actor_events") or []:
            if e.get("kind") != "cut_in" or e.get("closing_m_s") is None:
                continue
            ttc = _ttc(e, at_perceivable)
            if ttc is None:
                continue
            hit = failure.get("vehicle_id") == e.get("vehicle_id") and failure.get("hit") == "cut in by the tester"
            out.append({"closing_km_h": 3.6 * float(e["closing_m_s"]), "ttc_s": ttc, "scene": ep.get("scene"),
                        "blame": failure.get("blame") if hit else None})
    return out


def fig_cut_ins(rows: dict[str, list[dict[str, Any]]], colors: dict[str, str]) -> Any | None:
    """Each policy's cut-ins against R157's boundary (None: no cut-in): closing speed across, time-to-collision
    up, a cross where the ego hit the car (red: avoidable, grey: unavoidable for the careful driver)."""
    points = {p: cut_in_points(eps) for p, eps in rows.items()}
    if not any(points.values()):
        return None
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    right = max(65.0, max(q["closing_km_h"] for pts in points.values() for q in pts) + 5)
    speeds = [0.0, *(v for v, _ in R157_BOUNDARY), right]  # the boundary held beyond the regulation's ends
    ttcs = [r157_boundary_ttc(v) for v in speeds]
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
    ax.set_ylabel("time-to-collision [s] (10: not closing)")
    ax.set_ylim(0, 10.3)
    ax.set_xlim(0, right)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="center right")
    fig.tight_layout()
    return fig
