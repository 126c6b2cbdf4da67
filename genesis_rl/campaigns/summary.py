"""``summary.json``: per policy, mean violation scores with bootstrap 95% CIs, summed RSS deficit,
collisions and failure modes; paired comparisons of the agent against the baselines."""

from __future__ import annotations

import csv
import io
import json
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.campaign_files import read_campaign_meta, read_episode_row, read_step_records, steps_path
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.files.io_utils import atomic_write_json, atomic_write_text
from genesis_rl.core.files.spreadsheet import safe_rows
from genesis_rl.core.stats import bootstrap_mean_ci, paired_comparison
from genesis_rl.core.text import terminal_safe
from genesis_rl.labels.actor_summary import cut_in_markdown, cut_in_summary
from genesis_rl.labels.blame import blame_label, reference_name
from genesis_rl.labels.careful_driver import R157, careful_driver_evidence, event_for_collision
from genesis_rl.labels.distinct import natural_summary
from genesis_rl.labels.failure_modes import FAILURE_MODES, LABELLER_VERSION, FailureModeThresholds, label_collision
from genesis_rl.loop.rules.rulebook import Rulebook, build_rulebook
from genesis_rl.sim.interface import ActorEvent
from genesis_rl.world.step_record import StepRecord

#: Episode-row metrics summarised besides the rules' violations.
OTHER_METRICS = ("mean_iou", "return")
CSV_LEAD = ("policy", "scene", "episode_seed", "steps")
CSV_TAIL = ("collision_events", "first_collision_step", "collision_speed", "failure_mode", "min_gap", "mean_iou",
            "return", "sim_steps", "seconds", "record")


def campaign_rulebook(meta: dict[str, Any], rows: dict[str, list[dict[str, Any]]]) -> Rulebook:
    """The rulebook a campaign was scored with: stored in its identity since 0.5.0; for older campaigns (whose
    rules were all built in) rebuilt from the rule names of its episode rows."""
    stored = meta.get("identity", {}).get("rulebook")
    if stored:
        return build_rulebook(stored, "campaign.json identity.rulebook", stored_only=True)
    first = next((eps[0] for eps in rows.values() if eps), None)
    names = list(first["violations"]) if first else ["collision", "proximity", "rss_deficit"]
    return build_rulebook([{"name": n} for n in names], "campaign rulebook")


def metric_names(rulebook: Rulebook) -> list[str]:
    """The summarised metrics in order: the rule columns (``Rulebook.metric_columns``), IoU, return."""
    return [*rulebook.metric_columns(), *OTHER_METRICS]


def csv_columns(rulebook: Rulebook) -> list[str]:
    return [*CSV_LEAD, *rulebook.metric_columns(), *CSV_TAIL]


def load_campaign(folder: Path) -> tuple[dict[str, Any], dict[str, list[dict[str, Any]]]]:
    """The campaign's metadata and its finished episode rows by policy (in scene order)."""
    folder = Path(folder)
    meta = read_campaign_meta(folder)
    rows: dict[str, list[dict[str, Any]]] = {}
    for policy in meta["spec"]["policies"]:
        files = sorted(CampaignFolder(folder).policy_episodes(policy).glob("scene_*.json"))
        rows[policy] = [_current_labels(folder, policy, f) for f in files]
    return meta, rows


def _current_labels(folder: Path, policy: str, path: Path) -> dict[str, Any]:
    """An episode row, its collision relabelled (from its step Parquet) if an older labeller wrote it."""
    row = read_episode_row(path)
    if row.get("labeller_version") == LABELLER_VERSION:
        return row
    if row.get("first_collision_step") is not None:
        records = read_step_records(steps_path(folder, policy, row["scene"]), row.get("steps"))
        failure = label_collision(records)
        if failure and row.get("failure"):  # the conditions and naturalness stay; the mode is relabelled, and
            # a careful-driver verdict of an older reference is made again (with the blame it decides)
            failure = rejudge_careful_driver({**row["failure"], **failure}, row.get("actor_events") or [], records)
        row.update(failure=failure, failure_mode=failure["mode"] if failure else None)
    row["labeller_version"] = LABELLER_VERSION
    try:
        atomic_write_json(path, row, indent=1)
    except OSError:  # a read-only campaign: the relabelled row is used as it is, and relabelled next time again
        pass
    return row


def rejudge_careful_driver(failure: dict[str, Any], actor_events: list[dict[str, Any]],
                           records: list[StepRecord]) -> dict[str, Any]:
    """``failure`` with its careful-driver evidence and blame made again by today's reference, where an older one
    (another ``reference`` name) judged it: its verdict decides whether the failure counts, and the reference
    changed (a braking lead became critical once perceived). Other blames stay as the campaign made them."""
    careful = failure.get("careful_driver")
    if not isinstance(careful, dict) or careful.get("reference") == R157.name or len(records) < 2:
        return failure
    hit_at = next((i for i, r in enumerate(records) if r.collision.collided), None)
    event = None if hit_at is None else event_for_collision([ActorEvent.from_dict(e) for e in actor_events],
                                                            records, hit_at)
    if hit_at is None or event is None:
        return failure
    again = careful_driver_evidence(records, hit_at, event, records[1].time_s - records[0].time_s)
    return {**failure, "careful_driver": again, "reference": reference_name(again),
            "blame": blame_label(failure.get("evidence") or {}, failure.get("oracle_collides"), again)}


def summarize_campaign(folder: Path, write: bool = True,
                       loaded: tuple[dict[str, Any], dict[str, list[dict[str, Any]]]] | None = None) -> dict[str, Any]:
    """Aggregate the finished episodes (a half-finished campaign is summarised as far as it got, and says
    what is missing); writes summary.json and episodes.csv. ``loaded``: ``load_campaign``'s result, when
    the caller has read the campaign already."""
    folder = Path(folder)
    meta, rows = loaded or load_campaign(folder)
    rulebook = campaign_rulebook(meta, rows)
    rule_metrics = rulebook.metric_columns()
    seed = int(meta["spec"]["seed"])
    expected = len(meta["scenes"])
    policies: dict[str, Any] = {}
    for policy, eps in rows.items():
        stats: dict[str, Any] = {"episodes": len(eps), "missing": expected - len(eps)}
        for j, m in enumerate(metric_names(rulebook)):
            # seeded by the policy's name, so its interval does not depend on the order of --policies
            stats[m] = bootstrap_mean_ci([e[m] for e in eps if e[m] is not None],
                                         seed + zlib.crc32(policy.encode()) % 100_003 + j)
        for rule in rulebook.rules:
            if not rule.in_total:  # reported-only rules (the RSS deficit) are also summed over the episodes
                stats[f"{rule.name}_sum"] = round(sum(e[rule.name] for e in eps), 3)
        stats["episodes_with_collision"] = sum(1 for e in eps if e["collision_events"] > 0)
        stats["collision_events"] = sum(e["collision_events"] for e in eps)
        stats["failure_modes"] = {m: sum(1 for e in eps if e["failure_mode"] == m) for m in FAILURE_MODES}
        stats["sim_steps"] = sum(e["sim_steps"] for e in eps)
        natural = natural_summary(policy, eps)
        if natural is not None:
            stats["natural"] = natural
        cut_ins = cut_in_summary(eps)
        if cut_ins is not None:
            stats["cut_ins"] = cut_ins
        policies[policy] = stats
    comparisons: dict[str, Any] = {}
    if "agent" in rows:
        by_scene = {p: {e["scene"]: e for e in eps} for p, eps in rows.items()}
        for other in rows:
            if other == "agent":
                continue
            common = sorted(set(by_scene["agent"]) & set(by_scene[other]))
            comparisons[f"agent_vs_{other}"] = {
                m: paired_comparison([by_scene["agent"][s][m] for s in common],
                                     [by_scene[other][s][m] for s in common], seed + 7)
                for m in rule_metrics
            } | {"scenes": len(common)}
    complete = all(p["missing"] == 0 for p in policies.values())
    summary = {
        "campaign": str(folder), "complete": complete, "scenes": expected, "steps": meta["spec"]["steps"],
        "map": meta.get("catalog", {}).get("map", meta["spec"]["map"]), "seed": seed,
        "agent": meta["spec"].get("agent"),
        "bootstrap": {"resamples": 10_000, "level": 0.95, "method": "percentile"},
        "failure_mode_thresholds": FailureModeThresholds().as_dict(),
        "policies": policies, "comparisons": comparisons,
    }
    odd = meta.get("identity", {}).get("odd")
    if odd:
        summary["odd"] = odd
    if write:
        write_summary_files(folder, summary, rows, rulebook)
    return summary


def write_summary_files(folder: Path, summary: dict[str, Any], rows: dict[str, list[dict[str, Any]]],
                        rulebook: Rulebook) -> list[Path]:
    """Write ``summary.json`` and ``episodes.csv`` where their content changed; returns the files written.
    An unchanged file is left alone, so ``report`` on a finished campaign in a read-only folder writes nothing
    there (its ``--out`` goes elsewhere)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=csv_columns(rulebook), extrasaction="ignore")
    w.writeheader()
    for eps in rows.values():
        w.writerows(safe_rows(eps))  # a shared campaign's text must not run as a spreadsheet formula
    written = []
    for path, text in ((CampaignFolder(folder).summary, json.dumps(summary, indent=2)),
                       (CampaignFolder(folder).episodes_csv, buf.getvalue())):
        if not _holds(path, text):
            atomic_write_text(path, text)
            written.append(path)
    return written


def _holds(path: Path, text: str) -> bool:
    try:
        return path.is_file() and path.read_bytes() == text.encode("utf-8")  # bytes: csv ends its lines \r\n
    except OSError:
        return False


def summary_rule_metrics(summary: Mapping[str, Any]) -> list[str]:
    """The rule columns of a summary (violations and ``total``), in its order, read from the summary itself."""
    stats: Mapping[str, Any] = next(iter(summary["policies"].values()), {})
    return [k for k, v in stats.items() if isinstance(v, Mapping) and "mean" in v and k not in OTHER_METRICS]


def summary_markdown(summary: dict[str, Any]) -> str:
    """The policy table and the paired comparisons as Markdown (for docs and issue notes)."""

    def ci(s: dict[str, Any], digits: int = 2) -> str:
        if not s["n"] or s["mean"] is None:
            return "–"
        return f"{s['mean']:.{digits}f} [{s['ci_low']:.{digits}f}, {s['ci_high']:.{digits}f}]"

    rules = summary_rule_metrics(summary)
    sums = [k for k in next(iter(summary["policies"].values()), {}) if k.endswith("_sum")]
    head = ["policy", "episodes", *rules, *(f"{k[:-4]} summed" for k in sums), "episodes with collision",
            "failure modes", "mean IoU", "sim steps"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for p, s in summary["policies"].items():
        modes = ", ".join(f"{k} {v}" for k, v in s["failure_modes"].items() if v) or "–"
        cells = [p, str(s["episodes"]), *(ci(s[m]) for m in rules), *(f"{s[k]:.1f}" for k in sums),
                 str(s["episodes_with_collision"]), modes, ci(s["mean_iou"], 3), str(s["sim_steps"])]
        lines.append("| " + " | ".join(cells) + " |")
    natural = [(p, s["natural"]) for p, s in summary["policies"].items() if s.get("natural")]
    if natural:
        lines += ["", "| policy | collisions | inside the ODD | in-ODD collision rate [95% CI] | distinct in-ODD "
                  "failures | blame in / outside the ODD (perception, control, unavoidable) | naturalness per "
                  "episode / of the failures [nats] | steps inside / boundary / outside |", "|" + " --- |" * 8]
        for p, n in natural:
            r = n["in_odd_collision_rate"]
            rate = "–" if r["rate"] is None else \
                f"{100 * r['rate']:.0f}% [{100 * r['ci_low']:.0f}, {100 * r['ci_high']:.0f}]"
            splits = (n["blame"], n.get("outside_odd_blame", {}))
            blame = " / ".join(", ".join(str(v) for v in b.values()) for b in splits)
            fails = "–" if n["failure_naturalness_mean"] is None else f"{n['failure_naturalness_mean']:.3g}"
            steps = " / ".join(f"{100 * v:.0f}%" for v in n["odd_steps"].values()) if n["odd_steps"] else "–"
            lines.append(f"| {p} | {n['collisions']} | {n['in_odd_collisions']} | {rate} | "
                         f"{n['distinct_in_odd_failures']} | {blame} | {n['naturalness_mean']:.3g} / {fails} | "
                         f"{steps} |")
    lines += cut_in_markdown(summary["policies"])
    if summary["comparisons"]:
        lines += ["", "| comparison | metric | mean difference [95% CI] | wins / ties / losses | p (sign-flip) |",
                  "| --- | --- | --- | --- | --- |"]
        for name, comp in summary["comparisons"].items():
            for m in rules:
                c = comp[m]
                pv = "–" if c["p_value"] is None else f"{c['p_value']:.4f}"
                lines.append(f"| {name} | {m} | {ci(c['difference'])} | {c['wins']} / {c['ties']} / {c['losses']} "
                             f"| {pv} |")
    return terminal_safe("\n".join(lines) + "\n", keep="\n")  # names from a shared file print as text
