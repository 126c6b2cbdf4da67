"""The hardening's report: ``harden.png`` (held-out failure rate, what each attack found, clear-day precision and
recall, round by round) and ``harden.html`` (the same as a table, every round, those that did not help too)."""

from __future__ import annotations

import html
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from genesis_rl.core.files.io_utils import atomic_write, atomic_write_text


def _rate(test: Mapping[str, Any] | None) -> str:
    if not test or not test.get("rate"):
        return "-"
    r = test["rate"]
    return f"{r['k']}/{r['n']} = {r['rate']:.2f} [{r['ci_low']:.2f}, {r['ci_high']:.2f}]"


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _near(near: Mapping[str, Any] | None) -> str:
    """Near misses exported of those found (a hardening before 0.23.0, or --near-miss-ttc 0: -)."""
    if not near or not near.get("ttc_s"):
        return "-"
    return f"{near['exported']} of {near['found']} (TTC <= {near['ttc_s']:g} s)"


def clear_text(clear: Mapping[str, Any] | None) -> str:
    """Precision / recall; precision is undefined (-) for a detector that fired on nothing."""
    if not clear:
        return "-"
    return f"{_num(clear['precision'])} / {_num(clear['recall'])}"


def rates(result: Mapping[str, Any]) -> list[tuple[int, float, float, float]]:
    """(round, rate, low, high) of the held-out test, round 0 first."""
    out = []
    for rnd in [result["baseline"], *[r for r in result["rounds"] if r.get("test")]]:
        rate = rnd["test"]["rate"]
        out.append((int(rnd["round"]), float(rate["rate"]), float(rate["ci_low"]), float(rate["ci_high"])))
    return out


def retest_rates(result: Mapping[str, Any]) -> list[tuple[int, float, float, float]]:
    """(round, rate, low, high) of the wide re-test after the rounds (``--retest-scenes``), when there is one."""
    retest = result.get("retest") or {}
    return [(int(r["round"]), float(r["rate"]["rate"]), float(r["rate"]["ci_low"]), float(r["rate"]["ci_high"]))
            for r in retest.get("rounds", [])]


def plot(path: Path, result: Mapping[str, Any]) -> None:
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    rows = rates(result)
    ax = axes[0]
    xs = [r[0] for r in rows]
    ax.errorbar(xs, [r[1] for r in rows], yerr=[[r[1] - r[2] for r in rows], [r[3] - r[1] for r in rows]],
                fmt="o-", capsize=4, color="#c0392b", label=f"in the loop ({result['spec']['test_scenes']} scenes)")
    wide = retest_rates(result)
    if wide:
        ax.errorbar([r[0] + 0.12 for r in wide], [r[1] for r in wide],
                    yerr=[[r[1] - r[2] for r in wide], [r[3] - r[1] for r in wide]], fmt="s--", capsize=4,
                    color="#1f618d", label=f"re-test ({result['retest']['scenes']} scenes)")
        ax.legend(frameon=False, fontsize=8)
    rejected = {r["round"] for r in result["rounds"] if r["status"] == "seesaw"}
    for x, rate, _, _ in rows:
        if x in rejected:  # a rejected round's weights were not carried on
            ax.plot([x], [rate], "o", ms=11, mfc="white", mec="#7f8c8d", zorder=3)
            ax.annotate("seesaw:\nrejected", (x, rate), textcoords="offset points", xytext=(0, 12), ha="center",
                        fontsize=8, color="#7f8c8d")
    ax.set(xlabel="round (0: before)", ylabel="in-ODD failure rate per episode", xticks=xs,
           title="held-out re-test (95 % CI)")
    ax.set_ylim(bottom=0)
    ax = axes[1]
    attacks = [(r["round"], r["attack"]) for r in result["rounds"]]
    if result.get("final_attack"):
        attacks.append((len(result["rounds"]) + 1, result["final_attack"]))
    again = result.get("retrained_attack")
    bars = ax.bar([a[0] - 0.2 for a in attacks], [a[1]["in_odd_failures"] for a in attacks], width=0.4,
                  label="in-ODD failures", color="#e67e22")
    ax.bar_label(bars, fontsize=8)
    bars = ax.bar([a[0] + 0.2 for a in attacks], [a[1]["distinct"] for a in attacks], width=0.4, label="distinct",
                  color="#8e44ad")
    ax.bar_label(bars, fontsize=8)
    ticks = [a[0] for a in attacks]
    near = {r["round"]: (r.get("near_misses") or {}).get("exported", 0) for r in result["rounds"]}
    labels = [f"{t}\n+{near[t]} near" if near.get(t) else str(t) for t in ticks]
    if again:
        x = len(result["rounds"]) + 2
        ax.bar_label(ax.bar([x - 0.2], [again["in_odd_failures"]], width=0.4, color="#e67e22", hatch="//"), fontsize=8)
        ax.bar_label(ax.bar([x + 0.2], [again["distinct"]], width=0.4, color="#8e44ad", hatch="//"), fontsize=8)
        ticks, labels = [*ticks, x], [*labels, "re-trained"]
    ax.set_xticks(ticks, labels)
    ax.margins(y=0.12)
    ax.set(xlabel="attack against the weights of round (x - 1); +n near: near misses in its data", ylabel="found",
           title="what each attack found")
    ax.legend(frameon=False)
    ax = axes[2]
    clears = [(rnd["round"], rnd["clear"]) for rnd in [result["baseline"], *result["rounds"]] if rnd.get("clear")]
    if clears:
        base = result["baseline"].get("clear") or clears[0][1]
        tol = result["spec"]["tolerance"]
        for key, color in (("precision", "#2471a3"), ("recall", "#1e8449")):
            ax.plot([c[0] for c in clears], [c[1][key] if c[1][key] is not None else float("nan") for c in clears],
                    "o-", color=color, label=key)
            if base[key] is not None:
                ax.axhspan(base[key] - tol, base[key] + tol, color=color, alpha=0.12)
        ax.set(xticks=[c[0] for c in clears])
        ax.legend(frameon=False)
    ax.set(xlabel="round", title=f"clear day (band: before +- {result['spec']['tolerance']})")
    fig.suptitle(f"harden: {result['system']} on {result['map']}, attack '{result['spec']['campaign']}'")
    fig.tight_layout()
    atomic_write(path, lambda p: fig.savefig(p, dpi=100, format="png"))
    plt.close(fig)


def write_page(folder: Path, result: Mapping[str, Any]) -> None:
    """``harden.png`` and ``harden.html`` into ``folder``."""
    from genesis_rl.analysis.report import CSS

    plot(folder / "harden.png", result)
    spec = result["spec"]
    h = [f"<!doctype html><html><head><meta charset=utf-8><title>GENESIS-RL harden</title><style>{CSS}</style>"
         "</head><body>",
         f"<h1>Harden: {html.escape(result['system'])} on {html.escape(result['map'])}</h1>",
         f"<p class=meta>attack campaign {html.escape(spec['campaign'])}; {spec['rounds']} round(s); retrain "
         f"hook {html.escape(spec['retrain'])}; held-out re-test on {spec['test_scenes']} scenes; seesaw tolerance "
         f"{spec['tolerance']}; genesis-rl {html.escape(result['version'])}</p>"]
    if result.get("stopped"):
        h.append(f"<p><b>Stopped early:</b> {html.escape(result['stopped'])} (the same adversary, against the weights "
                 "the rounds before accepted), so there was nothing new to retrain on.</p>")
    h.append("<img src=harden.png alt='failure rate, attacks and clear-day metrics by round'>")
    h.append("<table><tr><th>round</th><th class=l>status</th><th>attack: in-ODD failures / episodes</th>"
             "<th>distinct</th><th>near misses</th><th>new frames</th>"
             "<th class=l>held-out in-ODD failure rate [95 % CI]</th>"
             "<th>clear precision / recall</th><th class=l>weights sha256</th></tr>")
    base = result["baseline"]
    h.append(f"<tr><td>0</td><td class=l>before</td><td>-</td><td>-</td><td>-</td><td>-</td>"
             f"<td class=l>{_rate(base['test'])}"
             f"</td><td>{clear_text(base.get('clear'))}</td>"
             f"<td class=l>{str(result.get('base_weights_sha256'))[:12]}</td></tr>")
    for rnd in result["rounds"]:
        status = rnd["status"]
        cls = "bad" if status == "seesaw" else "good"
        why = rnd.get("seesaw", {}).get("why", "")
        h.append(f"<tr><td>{rnd['round']}</td><td class='l {cls}'>{html.escape(status)}"
                 f"{' (' + html.escape(why) + ')' if why else ''}</td>"
                 f"<td>{rnd['attack']['in_odd_failures']} / {rnd['attack']['episodes']}</td>"
                 f"<td>{rnd['attack']['distinct']}</td><td>{_near(rnd.get('near_misses'))}</td>"
                 f"<td>{rnd.get('frames') or '-'}</td>"
                 f"<td class=l>{_rate(rnd.get('test'))}</td><td>{clear_text(rnd.get('clear'))}</td>"
                 f"<td class=l>{str(rnd.get('weights_sha256') or '-')[:12]}</td></tr>")
    final = result.get("final_attack")
    if final:
        h.append(f"<tr><td>final</td><td class=l>re-attack of the hardened system</td>"
                 f"<td>{final['in_odd_failures']} / {final['episodes']}</td><td>{final['distinct']}</td>"
                 "<td>-</td><td>-</td><td class=l>-</td><td>-</td>"
                 f"<td class=l>{str(result.get('final_weights_sha256') or '-')[:12]}</td></tr>")
    again = result.get("retrained_attack")
    if again:
        h.append(f"<tr><td>final</td><td class=l>an agent re-trained against the hardened system "
                 f"({html.escape(again['config'])})</td><td>{again['in_odd_failures']} / {again['episodes']}</td>"
                 f"<td>{again['distinct']}</td><td>-</td><td>-</td><td class=l>-</td><td>-</td>"
                 f"<td class=l>{str(result.get('final_weights_sha256') or '-')[:12]}</td></tr>")
    h.append("</table>")
    retest = result.get("retest")
    if retest:
        h.append(f"<h2>Re-test on {retest['scenes']} held-out scenes</h2><p class=meta>Every round's weights on the "
                 "same scenes and episode seeds of the re-test catalog, after the rounds. The fall is measured "
                 "from the accepted weights before the round.</p><table><tr><th>round</th><th class=l>status</th>"
                 "<th class=l>in-ODD failure rate [95 % CI]</th><th>distinct</th><th>fall</th></tr>")
        for row in retest["rounds"]:
            fell = "-" if row.get("fall") is None else f"{row['fall']:.0%}"
            h.append(f"<tr><td>{row['round']}</td><td class=l>{html.escape(row['status'])}</td>"
                     f"<td class=l>{_rate(row)}</td><td>{row['distinct']}</td><td>{fell}</td></tr>")
        h.append("</table>")
    estimates = result.get("estimates")
    if estimates:
        h.append(f"<h2>Failure rate under natural conditions ({html.escape(str(spec.get('member')))}, crude Monte "
                 "Carlo)</h2><table><tr><th class=l>weights</th><th>failed / episodes</th>"
                 "<th>per episode [95 % CI]</th></tr>")
        for when, est in estimates.items():
            lo, hi = est["ci95"]
            h.append(f"<tr><td class=l>{html.escape(when)}</td><td>{est['failures']} / {est['episodes']}</td>"
                     f"<td>{est['probability']:.3g} [{lo:.3g}, {hi:.3g}]</td></tr>")
        h.append("</table>")
    h.append("<p class=meta>A round's attack runs against the weights the round before accepted (round 1: "
             "the given campaign). Its data are the in-ODD failures' frames up to the impact and the near misses' "
             "(collision-free, time to collision with the lead at or below the line inside the ODD) up to the "
             "closest approach, rendered again from their records. A round whose clear-day precision or recall "
             "fell by more than the tolerance is marked seesaw and the next round starts from the weights before "
             "it.</p></body></html>")
    atomic_write_text(folder / "harden.html", "\n".join(h))
