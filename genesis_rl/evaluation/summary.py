"""``summary.json``: per policy, mean violation scores with bootstrap 95% CIs, summed RSS deficit,
collisions and failure modes; paired comparisons of the agent against the baselines."""

from __future__ import annotations

import csv
import io
import zlib
from pathlib import Path
from typing import Any

from genesis_rl.errors import UserInputError
from genesis_rl.evaluation.failure_modes import FAILURE_MODES, FailureModeThresholds
from genesis_rl.evaluation.stats import bootstrap_mean_ci, paired_comparison
from genesis_rl.io_utils import atomic_write_json, atomic_write_text, read_json

METRICS = ("collision", "proximity", "total", "rss_deficit", "mean_iou", "return")
CSV_COLUMNS = ("policy", "scene", "episode_seed", "steps", "collision", "proximity", "total", "rss_deficit",
               "collision_events", "first_collision_step", "collision_speed", "failure_mode", "min_gap",
               "mean_iou", "return", "sim_steps", "seconds", "record")


def load_campaign(folder: Path) -> tuple[dict[str, Any], dict[str, list[dict[str, Any]]]]:
    """The campaign's metadata and its finished episode rows by policy (in scene order)."""
    folder = Path(folder)
    meta_path = folder / "campaign.json"
    if not meta_path.is_file():
        raise UserInputError(f"'{folder}' is not a campaign folder (no campaign.json); run genesis-rl evaluate first")
    meta = read_json(meta_path, "campaign file")
    if meta.get("schema") != "genesis-rl/campaign" or meta.get("version") != 1:
        raise UserInputError(f"'{meta_path}' has schema {meta.get('schema')} version {meta.get('version')}; "
                             "this genesis-rl reads genesis-rl/campaign version 1")
    rows: dict[str, list[dict[str, Any]]] = {}
    for policy in meta["spec"]["policies"]:
        files = sorted((folder / "episodes" / policy).glob("scene_*.json"))
        rows[policy] = [_current_labels(folder, policy, f) for f in files]
    return meta, rows


def _current_labels(folder: Path, policy: str, path: Path) -> dict[str, Any]:
    """An episode row, its collision relabelled (from its step Parquet) if an older labeller wrote it."""
    from genesis_rl.evaluation.failure_modes import LABELLER_VERSION, label_collision

    row = read_json(path, "episode file")
    if row.get("labeller_version") == LABELLER_VERSION:
        return row
    if row.get("first_collision_step") is not None:
        import pyarrow.parquet as pq

        steps = folder / "steps" / policy / f"scene_{row['scene']:04d}.parquet"
        failure = label_collision(pq.read_table(steps).to_pylist())
        row.update(failure=failure, failure_mode=failure["mode"] if failure else None)
    row["labeller_version"] = LABELLER_VERSION
    atomic_write_json(path, row, indent=1)
    return row


def summarize_campaign(folder: Path, write: bool = True,
                       loaded: tuple[dict[str, Any], dict[str, list[dict[str, Any]]]] | None = None) -> dict[str, Any]:
    """Aggregate the finished episodes (a half-finished campaign is summarised as far as it got, and says
    what is missing); writes summary.json and episodes.csv. ``loaded``: ``load_campaign``'s result, when
    the caller has read the campaign already."""
    folder = Path(folder)
    meta, rows = loaded or load_campaign(folder)
    seed = int(meta["spec"]["seed"])
    expected = len(meta["scenes"])
    policies: dict[str, Any] = {}
    for policy, eps in rows.items():
        stats: dict[str, Any] = {"episodes": len(eps), "missing": expected - len(eps)}
        for j, m in enumerate(METRICS):
            # seeded by the policy's name, so its interval does not depend on the order of --policies
            stats[m] = bootstrap_mean_ci([e[m] for e in eps if e[m] is not None],
                                         seed + zlib.crc32(policy.encode()) % 100_003 + j)
        stats["rss_deficit_sum"] = round(sum(e["rss_deficit"] for e in eps), 3)
        stats["episodes_with_collision"] = sum(1 for e in eps if e["collision_events"] > 0)
        stats["collision_events"] = sum(e["collision_events"] for e in eps)
        stats["failure_modes"] = {m: sum(1 for e in eps if e["failure_mode"] == m) for m in FAILURE_MODES}
        stats["sim_steps"] = sum(e["sim_steps"] for e in eps)
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
                for m in ("collision", "proximity", "total", "rss_deficit")
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
    if write:
        atomic_write_json(folder / "summary.json", summary, indent=2)
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for eps in rows.values():
            w.writerows(eps)
        atomic_write_text(folder / "episodes.csv", buf.getvalue())
    return summary


def summary_markdown(summary: dict[str, Any]) -> str:
    """The policy table and the paired comparisons as Markdown (for docs and issue notes)."""

    def ci(s: dict[str, Any], digits: int = 2) -> str:
        if not s["n"] or s["mean"] is None:
            return "–"
        return f"{s['mean']:.{digits}f} [{s['ci_low']:.{digits}f}, {s['ci_high']:.{digits}f}]"

    lines = ["| policy | episodes | collision | proximity | total | RSS deficit / episode | RSS deficit summed | "
             "episodes with collision | failure modes | mean IoU | sim steps |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for p, s in summary["policies"].items():
        modes = ", ".join(f"{k} {v}" for k, v in s["failure_modes"].items() if v) or "–"
        lines.append(f"| {p} | {s['episodes']} | {ci(s['collision'])} | {ci(s['proximity'])} | {ci(s['total'])} | "
                     f"{ci(s['rss_deficit'])} | {s['rss_deficit_sum']:.1f} | {s['episodes_with_collision']} | "
                     f"{modes} | {ci(s['mean_iou'], 3)} | {s['sim_steps']} |")
    if summary["comparisons"]:
        lines += ["", "| comparison | metric | mean difference [95% CI] | wins / ties / losses | p (sign-flip) |",
                  "| --- | --- | --- | --- | --- |"]
        for name, comp in summary["comparisons"].items():
            for m in ("collision", "proximity", "total", "rss_deficit"):
                c = comp[m]
                pv = "–" if c["p_value"] is None else f"{c['p_value']:.4f}"
                lines.append(f"| {name} | {m} | {ci(c['difference'])} | {c['wins']} / {c['ties']} / {c['losses']} "
                             f"| {pv} |")
    return "\n".join(lines) + "\n"
