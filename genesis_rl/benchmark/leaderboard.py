"""The benchmark's figures: per member and policy, the falsifier metrics pooled over the trials, and the ranks
across the weakness members (``benchmark.ranks``); written as leaderboard.json and a page in the report's style.

Pooled over trials: every episode is a trial of the falsifier in ``benchmark.metrics``' sense (one scene
under the step budget), so the falsification rate, reached and triggered are shares of all episodes, with an
exact interval, and the survival curve is one Kaplan-Meier over all of them. Each trial's own rate is kept
too (its spread is what ARCH-COMP reports over its 10 runs). Distinct failures are counted over the union of
the trials' clusters (the same cluster found in two trials is one finding).
"""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from genesis_rl.analysis.estimate_files import estimate_line
from genesis_rl.benchmark.metrics import PolicyMetrics, falsifier_metrics
from genesis_rl.benchmark.ranks import compare_ranks
from genesis_rl.benchmark.survival import kaplan_meier, median_time
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json
from genesis_rl.core.stats import clopper_pearson
from genesis_rl.labels.distinct import KEY_FIELDS
from genesis_rl.sut.zoo.members import zoo_member


def _mean(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return round(sum(known) / len(known), 1) if known else None


def pooled(policy: str, member: str, per_trial: list[PolicyMetrics], rerun: bool = False,
           baseline: list[PolicyMetrics] | None = None) -> dict[str, Any]:
    """One policy's figures on one member over its trials (module docstring); ``rerun``: the benchmark re-ran
    reported failures on fresh world seeds (``benchmark.reproduce``), so the primary score asks them to
    reproduce; ``baseline``: ``sunny``'s trials on the same scenes, when it played: on a control, a false-alarm
    candidate on a scene where the held weather fails inside the ODD too is the system's own failure, not one
    the adversary caused (``false_alarms_beyond_sunny``)."""
    trials = [t for m in per_trial for t in m.trials]
    n = len(trials)
    kind = zoo_member(member).kind
    control = kind == "control"
    confirmed = sum(t.confirmed(control, rerun) for t in trials)
    confirmed_ci = clopper_pearson(confirmed, n)
    again = [t for t in trials if t.reruns]
    falsified = sum(t.failed for t in trials)
    ci = clopper_pearson(falsified, n)
    t, s = kaplan_meier([tr.steps_to_failure for tr in trials], [tr.failed for tr in trials])
    keys = {tuple(str(c.get(k)) for k in KEY_FIELDS) for m in per_trial for c in m.clusters}
    alarms = [a for m in per_trial for a in m.false_alarm_candidates]
    return {
        "policy": policy, "member": member, "kind": kind, "trials": len(per_trial),
        "episodes": n, "confirmed": confirmed, "confirmed_rate": None if n == 0 else round(confirmed / n, 4),
        "confirmed_ci": [confirmed_ci["ci_low"], confirmed_ci["ci_high"]], "rerun": rerun,
        "reported_failures": sum(t.failure_at is not None for t in trials),
        "reproduction_rate": (round(sum(t.reproduced for t in again) / sum(t.reruns for t in again), 4)
                              if again else None),
        "reproducible": sum(t.reproducible for t in trials),
        "falsified": falsified, "avoidable": sum(t.avoidable for t in trials),
        "falsification_rate": None if n == 0 else round(falsified / n, 4),
        "falsification_ci": [ci["ci_low"], ci["ci_high"]],
        "falsification_rate_per_trial": [m.falsification_rate for m in per_trial],
        "trials_with_a_failure": sum(m.falsified > 0 for m in per_trial),
        "reached": sum(tr.reached for tr in trials), "triggered": sum(tr.triggered for tr in trials),
        "survival": [[float(a), float(b)] for a, b in zip(t, s, strict=True)],
        "budget_steps": max((tr.steps for tr in trials), default=0),
        "sim_steps_per_scene": _mean([m.sim_steps_per_scene for m in per_trial]),
        "median_steps_to_failure": median_time(t, s),
        "distinct_in_odd_failures": len(keys),
        "false_alarm_candidates": len(alarms),
        "unconfirmed_false_alarms": sum(1 for a in alarms if a.get("oracle_collides") is False),
        "false_alarms_beyond_sunny": None if baseline is None else _beyond(per_trial, baseline),
    }


def _beyond(per_trial: Sequence[PolicyMetrics], baseline: Sequence[PolicyMetrics]) -> int:
    """The false-alarm candidates on scenes where the baseline (sunny, the held start weather) had no in-ODD
    failure in the same trial: what the adversary's weather added to the system's own failures."""
    count = 0
    for mine, base in zip(per_trial, baseline, strict=True):
        own = {t.scene for t in base.trials if t.failure_at is not None}
        count += sum(1 for a in mine.false_alarm_candidates if a["scene"] not in own)
    return count


def leaderboard(spec: Mapping[str, Any], trials: Mapping[str, Sequence[Path]],
                agent_trials: Mapping[str, Mapping[str, Sequence[Path]]] | None = None,
                out: Path | None = None) -> dict[str, Any]:
    """Every (member, policy) pooled over the trials, and the ranks over the weakness members (score: the share
    of confirmed failures, reproducible, triggered and avoidable, ties broken by the median steps to the first
    failure, fewer first). ``spec``: the
    benchmark's spec as ``BenchmarkSpec.to_json`` writes it; ``trials``: each member's campaign folders;
    ``out``: the benchmark folder, whose ``reproductions/`` hold the re-runs (when ``spec['reruns']`` > 0);
    ``agent_trials``: per member, each trained agent's label (``agent:RUN``) and its campaign folders. An agent
    is trained per member, so its cells stand beside the adversaries' and stay out of the rank test, whose
    policies must be the same on every member."""
    from genesis_rl.benchmark.reproduce import load_reproductions, reproduction_file

    members, policies = list(spec["members"]), list(spec["policies"])
    rerun = bool(spec.get("reruns")) and out is not None

    def again(member: str, folder: Path) -> dict[str, dict[int, tuple[int, int]]]:
        return load_reproductions(reproduction_file(out, member, folder)) if rerun and out is not None else {}

    cells: dict[str, dict[str, Any]] = {}
    for member in members:
        per_policy: dict[str, list[PolicyMetrics]] = {p: [] for p in policies}
        for folder in trials[member]:
            for policy, metrics in falsifier_metrics(folder, member, again(member, folder)).items():
                per_policy.setdefault(policy, []).append(metrics)
        sunny = per_policy.get("sunny") if zoo_member(member).kind == "control" else None
        base = sunny if sunny and len(sunny) == len(trials[member]) else None
        cells[member] = {p: pooled(p, member, per_policy[p], rerun, base) for p in policies}
        for label, folders in (agent_trials or {}).get(member, {}).items():
            cells[member][label] = pooled(label, member, [falsifier_metrics(f, member, again(member, f))["agent"]
                                                          for f in folders], rerun, base)
    weak = [m for m in members if zoo_member(m).kind == "weakness"]

    def score(c: dict[str, Any]) -> float:
        rate = c["confirmed_rate"] or 0.0
        med = c["median_steps_to_failure"]
        return rate - (0.0 if med is None else med * 1e-9)  # faster breaks a tie in the rate

    ranks = compare_ranks({m: {p: score(cells[m][p]) for p in policies} for m in weak}, policies)
    return {"spec": dict(spec), "cells": cells, "ranks": ranks,
            "controls": [m for m in members if zoo_member(m).kind == "control"], "weaknesses": weak}


def write_leaderboard(out: Path, board: dict[str, Any]) -> None:
    atomic_write_json(Path(out) / "leaderboard.json", board, indent=1)
    page = render_page(board)
    atomic_write(Path(out) / "leaderboard.html", lambda p: p.write_text(page))


def _fig_survival(board: dict[str, Any], member: str) -> str:
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    from genesis_rl.analysis.report import figure_png_base64, policy_color

    fig, ax = plt.subplots(figsize=(5.2, 3.2))
    agents = 0
    for k, (policy, c) in enumerate(board["cells"][member].items()):
        pts = c["survival"]
        xs = [p[0] for p in pts] + [float(c["budget_steps"])]  # flat to the budget, where the rest are censored
        ys = [p[1] for p in pts] + [pts[-1][1]]
        # trained agents dashed, each its own colour, so that they never share one with an adversary
        agent = policy.startswith("agent:")
        color = AGENT_COLORS[agents % len(AGENT_COLORS)] if agent else policy_color(policy, k)
        agents += agent
        ax.step(xs, ys, where="post", color=color, ls="--" if agent else "-",
                label=f"{policy} ({c['falsified']}/{c['episodes']})")
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("simulator steps")
    ax.set_ylabel("share without an in-ODD failure")
    ax.set_title(member, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # beside the curves, not over them
    return figure_png_base64(fig)


#: the trained agents' curves (dashed): colours no adversary of the report's palette uses
AGENT_COLORS = ("#e6194b", "#3cb44b", "#4363d8", "#f58231", "#911eb4", "#42d4f4")


def _fig_ranks(board: dict[str, Any]) -> str | None:
    r = board["ranks"]
    avg = {p: v for p, v in r["average_rank"].items() if v is not None}
    if not avg:
        return None
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    from genesis_rl.analysis.report import figure_png_base64, policy_color

    fig, ax = plt.subplots(figsize=(5.2, 1.6 + 0.25 * len(avg)))
    order = sorted(avg, key=lambda p: avg[p])
    for k, p in enumerate(order):
        ax.plot([avg[p]], [k], "o", color=policy_color(p, k))
        ax.annotate(p, (avg[p], k), xytext=(6, -3), textcoords="offset points", fontsize=8)
    cd = r.get("critical_difference")
    if cd:
        ax.plot([1.0, 1.0 + cd], [-0.8, -0.8], color="#333", lw=2)
        ax.annotate(f"CD = {cd:.2f}", (1.0, -0.8), xytext=(0, 4), textcoords="offset points", fontsize=8)
    ax.set_yticks([])
    ax.set_ylim(-1.3, len(order) - 0.4)
    ax.set_xlim(0.8, len(r["average_rank"]) + 0.7)
    ax.set_xlabel("average rank over the weakness members (1: best)")
    ax.grid(axis="x", alpha=0.3)
    return figure_png_base64(fig)


def _transfer_table(board: dict[str, Any], member: str) -> list[str]:
    """Under the transfer protocol: what each policy cost in simulator steps (tuning and training included), the
    tuning scene each search's schedule came from, and each trained agent's break-even count of held-out
    scenes; nothing under the per-scene protocol."""
    transfer = (board.get("transfer") or {}).get("members", {}).get(member)
    if not transfer:
        return []
    costs, chosen, even = transfer["costs"], transfer["tuned"], transfer["break_even_scenes"]
    searches = sorted({s for row in even.values() for s in row})
    h = ["<p class=meta>Transfer protocol: each search tuned on its own scenes and replayed its best schedule once "
         "on every held-out scene above. Simulator steps, summed over the trials:</p><table><tr>"
         + "".join(f"<th class=l>{c}</th>" for c in ("policy", "tuning", "training", "held-out", "in all",
                                                     "schedule from tuning scene (hit)",
                                                     *[f"break-even scenes vs {s}" for s in searches])) + "</tr>"]

    def num(v: Any) -> str:
        return "–" if v is None else f"{v:,.0f}" if isinstance(v, int) else f"{v:,.1f}"

    for policy, c in costs.items():
        picks = ", ".join(f"{p['scene']} ({'yes' if p['hit'] else 'no'})" for p in chosen.get(policy, [])) or "–"
        row = [policy, num(c["tuning_steps"]), num(c["training_steps"]), num(c["held_out_steps"]),
               num(c["total_steps"]), picks]
        row += [("never" if even[policy].get(s) is None else num(even[policy][s])) if policy in even else "–"
                for s in searches]
        h.append("<tr>" + "".join(f"<td class=l>{html.escape(x)}</td>" for x in row) + "</tr>")
    h.append("</table>")
    seen = {a: n for a, n in (transfer.get("held_out_scenes_seen_in_training") or {}).items() if n != 0}
    if seen:
        h.append("<p class=meta>Held-out scenes a trained agent trained on (its run generated them: same map, "
                 "catalog seed and traffic): " + html.escape(", ".join(
                     f"{a}: {'unknown (a catalog file)' if n is None else n}" for a, n in seen.items()))
                 + ". Its held-out figures are not on unseen scenes there.</p>")
    if searches:
        h.append("<p class=meta>Break-even: the held-out scenes after which a trained agent's simulator steps per "
                 "confirmed failure (its training once, one episode a scene) drop to the search's (its tuning of "
                 "one trial, one episode a scene); never: the agent confirms fewer failures a scene.</p>")
    return h


def render_page(board: dict[str, Any]) -> str:
    """The leaderboard as one self-contained HTML page."""
    from genesis_rl import __version__
    from genesis_rl.analysis.report import CSS

    spec = board["spec"]
    h = [f"<!doctype html><html><head><meta charset=utf-8><title>GENESIS-RL benchmark</title><style>{CSS}</style>"
         "</head><body><h1>GENESIS-RL benchmark: adversaries against systems with known weaknesses</h1>",
         f"<p class=meta>{len(spec['members'])} zoo members x {len(spec['policies'])} policies x {spec['trials']} "
         f"trials (seeds {spec['seed']}..{spec['seed'] + spec['trials'] - 1}), {spec['scenes']} scene(s) a trial, "
         f"{spec['steps'] or 'each member’s own'} steps an episode · "
         + ("transfer protocol: searches tuned on "
            f"{spec.get('tuning_scenes')} other scene(s) a trial, one episode a held-out scene · "
            if spec.get("protocol") == "transfer" else "")
         + f"genesis-rl {__version__} · docs/zoo.md</p>"]
    r = board["ranks"]
    if board["weaknesses"]:
        h.append("<h2>Ranks over the weakness members</h2>")
        img = _fig_ranks(board)
        if img:
            h.append(f"<img src='{img}'>")
        p = r.get("friedman_p")
        h.append("<p class=meta>Score on a member: the share of confirmed failures, triggered, avoidable and "
                 "reproducible on fresh world seeds (ties: fewer steps to the first failure). "
                 + (f"Friedman's test over {len(r['systems'])} members (ties corrected): chi2 = {r['friedman_chi2']}, "
                    f"p = {p}; Iman-Davenport F = {r.get('iman_davenport_f')}, p = {r.get('iman_davenport_p')}; "
                    f"Nemenyi critical difference at 5 %: {r['critical_difference']}." if p is not None else
                    "Friedman's test needs at least 2 weakness members and 2 policies.") + "</p>")
    head = ["policy", "episodes", "simulator steps a scene", "confirmed [95 % CI]", "reproduction rate",
            "in-ODD collisions, any candidate [95 % CI]", "trials with a failure",
            "avoidable", "reached", "triggered",
            "median steps to first failure", "distinct in-ODD failures",
            "false-alarm candidates (unconfirmed; beyond sunny)"]
    for member in spec["members"]:
        m = zoo_member(member)
        h.append(f"<h2>{html.escape(member)} <span class=meta>({m.kind})</span></h2>"
                 f"<p class=meta>{html.escape(m.summary)}</p>")
        rate = (board.get("estimates") or {}).get(member)
        if rate:
            h.append(f"<p>{html.escape(estimate_line(rate))}</p>")
        h.append("<table><tr>" + "".join(f"<th class=l>{c}</th>" for c in head) + "</tr>")
        for policy, c in board["cells"][member].items():
            lo, hi = c["falsification_ci"]
            rate = "–" if c["falsification_rate"] is None else \
                f"{c['falsification_rate']:.2f} [{lo:.2f}, {hi:.2f}]"
            med = "–" if c["median_steps_to_failure"] is None else f"{c['median_steps_to_failure']:.0f}"
            beyond = c.get("false_alarms_beyond_sunny")
            alarms = f"{c['false_alarm_candidates']} ({c['unconfirmed_false_alarms']}; " \
                     f"{'–' if beyond is None else beyond} beyond sunny)" if m.kind == "control" else "–"
            spend = "–" if c.get("sim_steps_per_scene") is None else f"{c['sim_steps_per_scene']:.0f}"
            avoidable = "–" if c.get("avoidable") is None else f"{c['avoidable']}/{c['falsified']}"
            clo, chi = c.get("confirmed_ci") or (None, None)
            confirmed = "–" if c.get("confirmed_rate") is None else \
                f"{c['confirmed']} = {c['confirmed_rate']:.2f} [{clo:.2f}, {chi:.2f}]"
            again = "not re-run" if not c.get("rerun") else ("–" if c.get("reproduction_rate") is None else
                                                            f"{c['reproduction_rate']:.2f}")
            cells = [policy, str(c["episodes"]), spend, confirmed, again, rate,
                     f"{c['trials_with_a_failure']}/{c['trials']}",
                     avoidable, str(c["reached"]), str(c["triggered"]), med, str(c["distinct_in_odd_failures"]), alarms]
            h.append("<tr>" + "".join(f"<td class=l>{html.escape(x)}</td>" for x in cells) + "</tr>")
        h.append("</table>")
        h.extend(_transfer_table(board, member))
        h.append(f"<img src='{_fig_survival(board, member)}'>")
    h.append("<p class=meta>Confirmed: the reported episode's in-ODD failure is triggered (on a control: any), not "
             "blamed unavoidable, and reproduces in at least half of its re-runs on fresh world seeds (traffic, "
             "sensor noise and the system's own draws that no adversary saw; a policy that does not react replays "
             "its schedule, one that reacts plays again). Reproduction rate: the share of those re-runs that failed "
             "again. In-ODD collisions counts a search's every candidate, whether or not it reported it. "
             "Simulator steps a scene: what the policy spent on each scene (a search counts every "
             "candidate episode; re-runs are the benchmark's, not the policy's): adversaries at unequal budgets "
             "are compared at unequal cost. "
             "Avoidable: failed episodes less those blamed unavoidable (the careful driver collides as well; a "
             "search counts as its reported episode). Reached: the episode entered the member's trigger region; "
             "triggered: an in-ODD failure "
             "at or after that. Never reached says exploration; reached, never triggered, timing or naturalness. "
             "On a control every in-ODD failure is a false-alarm candidate; unconfirmed: the oracle replay "
             "avoided it; beyond sunny: on a scene where sunny (the held start weather) had no in-ODD failure in "
             "the same trial, so the failure is not the system's own whatever the weather (scene 39 of "
             "builtin_highway is one it has anyway).</p></body></html>")
    return "\n".join(h)
