"""The report's first section for a campaign run inside an operational design domain: what a safety engineer
reads first.

1. One line per policy: how many *distinct* failures it found inside the ODD, how many collisions inside the
   ODD that is (with an exact 95% CI on the rate), the blame split and how natural their weather was.
2. The ODD coverage map: where in (visibility, ego speed) each policy spent its steps, the ODD's visibility
   bound, the speed that stops within the visibility (dry and wet road: the failure boundary a driver keeps
   to), and every collision marked (filled inside the ODD, hollow outside).
3. The distinct-failure table, ordered by rulebook priority (collisions first), blame (perception, control,
   unavoidable) and naturalness, each cluster with its most natural member's frames and replay command.
"""

from __future__ import annotations

import html
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.labels.blame import BLAMES
from genesis_rl.loop.rules.rulebook import speed_for_visibility
from genesis_rl.world.step_record import StepRecord

StepsOf = Callable[[str, int], list[StepRecord]]


def lead_lines(summary: dict[str, Any]) -> list[str]:
    """'random: 3 distinct in-ODD failures (7 in-ODD collisions in 50 episodes, 14% [6%, 27%]) ...'."""
    out = []
    for policy, s in summary["policies"].items():
        n = s.get("natural")
        if n is None:
            continue
        rate = n["in_odd_collision_rate"]
        where = "in-ODD" if n["odd"] else ""
        ci = "" if rate["rate"] is None else \
            f", {100 * rate['rate']:.0f}% [{100 * rate['ci_low']:.0f}%, {100 * rate['ci_high']:.0f}%]"
        blame = ", ".join(f"{k} {v}" for k, v in n["blame"].items() if v) or "none"
        nat = "" if n["failure_naturalness_mean"] is None else \
            f"; their weather's naturalness {n['failure_naturalness_mean']:.3g} nats (0: weather held)"
        outside = n["collisions"] - n["in_odd_collisions"]
        beyond = ""
        if outside:
            split = ", ".join(f"{k} {v}" for k, v in n.get("outside_odd_blame", {}).items() if v)
            beyond = f"; <b>{outside} more outside the ODD</b>" + (f" (blame: {split})" if split else "")
        unavoidable = n["blame"].get("unavoidable", 0)
        refs = ", ".join(f"{html.escape(k)} {v}" for k, v in n.get("references", {}).items())
        own = "" if not unavoidable else \
            (f"; {n.get('distinct_avoidable_in_odd_failures', '?')} distinct avoidable: {unavoidable} unavoidable "
             "collision(s) are not counted against the system")
        decided = f" (decided by: {refs})" if refs else ""
        out.append(f"<b>{html.escape(policy)}</b>: <b>{n['distinct_in_odd_failures']} distinct {where} "
                   f"failure(s)</b> ({n['in_odd_collisions']} {where} collisions in {rate['n']} episodes{ci}); "
                   f"blame: {blame}{decided}{own}{nat}{beyond}")
    return out


def fig_odd_coverage(summary: dict[str, Any], rows: dict[str, list[dict[str, Any]]], steps_of: StepsOf,
                     png: Callable[[Any], str], max_points: int = 4000) -> str | None:
    """One panel per policy: its steps in (visibility, ego speed), the ODD bound, the failure boundary."""
    from genesis_rl.core.plotting import plain_log_ticks, pyplot

    plt = pyplot()

    policies = [p for p in rows if summary["policies"][p].get("natural")]
    if not policies:
        return None
    odd = summary.get("odd") or {}
    vmin = odd.get("visibility", {}).get("min")
    fig, axes = plt.subplots(1, len(policies), figsize=(4.2 * len(policies) + 1.8, 3.8), squeeze=False, sharey=True)
    vis_axis = np.geomspace(8, 4000, 200)
    for ax, policy in zip(axes[0], policies, strict=True):
        vis, speed, status = [], [], []
        hits = []
        for e in rows[policy]:
            recs = steps_of(policy, e["scene"])
            for r in recs:
                if r.conditions is not None:
                    vis.append(r.conditions.visibility_m)
                    speed.append(r.ego.speed)
                    status.append(r.odd_status)
            f = e.get("failure")
            if f and f.get("conditions"):
                inside = f.get("odd_status") in ("inside", "boundary")
                hits.append((f["conditions"]["visibility_m"], f["speed"], inside))
        rng = np.random.default_rng(0)
        idx = rng.permutation(len(vis))[:max_points]
        v, s = np.array(vis)[idx], np.array(speed)[idx]
        outside = np.array([status[i] == "outside" for i in idx], bool)
        ax.scatter(v[~outside], s[~outside], s=3, alpha=0.25, color="#2c7fb8", label="steps in the ODD")
        if outside.any():
            ax.scatter(v[outside], s[outside], s=3, alpha=0.25, color="#bbbbbb", label="steps outside")
        for road, style in (("dry", "-"), ("wet", "--")):
            ax.plot(vis_axis, [speed_for_visibility(x, road) for x in vis_axis], "k" + style, lw=1,
                    label=f"stops within visibility ({road})")
        if vmin:
            ax.axvspan(1, vmin, color="#f4cccc", alpha=0.5, label=f"outside the ODD (< {vmin:g} m)")
        for x, y, inside in hits:
            ax.scatter([x], [y], s=60, marker="X", color="#c0392b" if inside else "white", edgecolor="#c0392b",
                       zorder=5)
        ax.set_xscale("log")
        plain_log_ticks(ax.xaxis)  # the log scale's own labels are mathtext, which the package's figures turn off
        ax.set_xlim(8, 4000)
        ax.set_ylim(0, max([12.0, *speed]) * 1.1)
        ax.set_xlabel("visibility [m]")
        ax.set_title(f"{policy}: {len(hits)} collision(s)", fontsize=10)
    axes[0][0].set_ylabel("ego speed [m/s]")
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), markerscale=3)
    fig.tight_layout()
    return png(fig)


def _short_reference(reference: Any) -> str:
    """The reference's name as the table shows it ("–" for campaigns written before references existed)."""
    if not reference:
        return "–"
    return "R157 careful driver" if "R157" in str(reference) else "visibility, stopping distance"


def cluster_rows(summary: dict[str, Any]) -> list[dict[str, Any]]:
    """Every policy's clusters in one list, ordered by rule priority (all are collisions), blame and
    naturalness (most natural first)."""
    out = []
    for policy, s in summary["policies"].items():
        for c in (s.get("natural") or {}).get("clusters", []):
            out.append({**c, "policy": policy})
    order = {b: i for i, b in enumerate(BLAMES)}
    out.sort(key=lambda c: (order.get(c["blame"], len(order)), -(c["members"][0]["naturalness"] or -np.inf)))
    return out


def section(folder: Path, summary: dict[str, Any], rows: dict[str, list[dict[str, Any]]], steps_of: StepsOf,
            png: Callable[[Any], str], frame_strip: Callable[[str, int, list[StepRecord]], str | None],
            max_frames: int = 6) -> list[str]:
    """The section's HTML (empty for a campaign without natural-edge-case data)."""
    lines = lead_lines(summary)
    if not lines:
        return []
    odd = summary.get("odd")
    h = ["<h2>0. Natural edge cases: distinct failures inside the ODD</h2>"]
    if odd:
        h.append(f"<p class=meta>ODD <b>{html.escape(odd['name'])}</b>: {html.escape(odd.get('description', ''))}"
                 "</p>")
    else:
        h.append("<p class=meta>No ODD was declared: every failure counts, and none is labelled inside or "
                 "outside (<code>--odd configs/odd/NAME.toml</code>).</p>")
    h.append("<ul>" + "".join(f"<li>{line}</li>" for line in lines) + "</ul>")
    fig = fig_odd_coverage(summary, rows, steps_of, png)
    if fig:
        h.append(f"<img src='{fig}'><p class=meta>Each point is a step. Black: the speed that stops within the "
                 "visibility (UK Highway Code stopping distances; dashed: wet road); above it a driver is too fast "
                 "for the conditions. Red crosses: collisions inside the ODD; hollow: outside.</p>")
    clusters = cluster_rows(summary)
    if not clusters:
        h.append("<p>No collision inside the ODD.</p>")
        return h
    head = ["#", "policy", "failure mode", "blame", "decided by", "ODD", "visibility", "rain", "light", "road", "hit",
            "count", "most natural: scene", "naturalness [nats]"]
    h.append("<table><tr>" + "".join(f"<th class=l>{c}</th>" for c in head) + "</tr>")
    for i, c in enumerate(clusters, 1):
        rep = c["members"][0]
        cells = [str(i), c["policy"], c["mode"], c["blame"], _short_reference(c.get("reference")), c["odd_status"],
                 c["visibility"], c["rain"], c["light"],
                 c["road_state"], c["hit"], str(c["count"]), str(rep["scene"]),
                 "–" if rep["naturalness"] is None else f"{rep['naturalness']:.3g}"]
        h.append("<tr>" + "".join(f"<td class=l>{html.escape(x)}</td>" for x in cells) + "</tr>")
    h.append("</table><p class=meta>Two failures are the same when mode, blame, ODD status, the conditions' bands "
             "and what was hit agree (docs/odd.md). Blame: <i>perception</i>, ground-truth perception (the oracle "
             "replay) avoids it; <i>control</i>, the vehicle was visible with room to stop, or the ego drove too "
             "fast for the visibility; <i>unavoidable</i>, neither. When the tester's actor knob acted on the "
             "vehicle hit (a cut-in, the lead braking), UN R157's competent and careful driver decides instead: "
             "perceives after 0.4 s, reacts after 0.75 s more (to a braking lead at once, to a cut-in once it is "
             "critical), brakes at up to 0.774 g; the collision is "
             "<i>unavoidable</i> when that driver collides too, and is then not the system's failure "
             "(docs/actors.md).</p>")
    for i, c in enumerate(clusters[:max_frames], 1):
        rep = c["members"][0]
        strip = frame_strip(c["policy"], rep["scene"], steps_of(c["policy"], rep["scene"]))
        h.append(f"<div class=card><h3>#{i} {html.escape(c['mode'])}, {html.escape(c['blame'])}: "
                 f"{html.escape(str(c['policy']))}, scene {html.escape(str(rep['scene']))}</h3>")
        if strip:
            h.append(f"<img src='{strip}'>")
        if rep.get("record"):
            h.append(f"<p class=meta>Replay: <code>genesis-rl replay {html.escape(str(folder / rep['record']))} "
                     f"--out replay_{html.escape(str(c['policy']))}_{html.escape(str(rep['scene']))}</code></p>")
        h.append("</div>")
    return h
