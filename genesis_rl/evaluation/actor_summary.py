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
