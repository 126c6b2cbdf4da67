"""``report.html``: one self-contained page (figures embedded) that tells a campaign's story.

0. For a campaign from 0.6.0 on: distinct failures inside the ODD, the ODD coverage map, blame and
   naturalness (``report_natural``).
1. The paper's Fig. 2: the mean violation of every rule of the campaign's rulebook per policy (the paper's:
   collision, proximity, RSS deficit), with bootstrap 95% CIs, and the paired agent-vs-baseline comparison.
2. Fig. 3-style telemetry for one collision per failure mode: speeds, throttle and brake, true and
   perceived distance to the lead, and whether the hit vehicle was detected.
3. Camera frames before each of those collisions, with true (green) and detected (orange) boxes.
4. The knobs each policy turned, step by step (mean over scenes, 10-90% band).
5. A per-scene table.
A campaign that is not finished is reported as far as it got, with what is missing said at the top.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from genesis_rl.adversaries.agent import agent_learning_curve
from genesis_rl.analysis.estimate_files import check_same_system, estimate_line, load_estimate
from genesis_rl.analysis.report_natural import section as natural_section
from genesis_rl.campaigns.campaign_files import campaign_named_files, read_step_records, read_steps, steps_path
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.campaigns.summary import campaign_rulebook, load_campaign, summarize_campaign, write_summary_files
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import os_error_message
from genesis_rl.core.parsing import read_json
from genesis_rl.labels.actor_summary import cut_in_html, fig_cut_ins
from genesis_rl.labels.failure_modes import FAILURE_MODES, detection_timeline
from genesis_rl.loop.frames import annotate_frame
from genesis_rl.loop.rules.rulebook import Rulebook
from genesis_rl.world.knobs import KNOBS, PAPER_KNOBS, Weather
from genesis_rl.world.step_record import StepRecord

POLICY_COLORS = {"sunny": "#f2a900", "random": "#7f8c8d", "agent": "#c0392b", "cmaes": "#2c7fb8", "cem": "#31a354",
                 "constant": "#756bb1", "mcts": "#e7298a", "random_search": "#3d3d3d"}
MODE_TITLES = {"non_detection": "Non-detection", "intermittent_detection": "Intermittent detection",
               "delayed_detection": "Delayed detection", "lost_detection": "Lost before impact",
               "detected": "Detected in time (control failure)",
               "out_of_view": "Hit vehicle out of view"}


def _esc(value: object) -> str:
    """Any value from a campaign's files as HTML text: a shared campaign's strings never become markup."""
    return html.escape(str(value), quote=False)  # text, never inside an attribute


def policy_color(policy: str, k: int) -> str:
    return POLICY_COLORS.get(policy, ["#8e44ad", "#16a085", "#d35400", "#2d3436"][k % 4])


def figure_png_base64(fig: Any) -> str:
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _jpeg(rgb: np.ndarray) -> str:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=88)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode()


def fig_comparison(summary: dict[str, Any], rulebook: Rulebook) -> str:
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    pols = list(summary["policies"])
    # a panel per rule: its name and unit, its description wrapped so that neighbouring titles do not overlap
    metrics = [(r.name, f"{r.name.replace('_', ' ')}" + (f" [{r.unit}]" if r.unit else "") + "\n"
                + textwrap.fill(r.description.split(" [")[0], 38)) for r in rulebook.rules]
    fig, axes = plt.subplots(1, len(metrics), figsize=(4 * len(metrics), 3.6), squeeze=False)
    for ax, (m, title) in zip(axes[0], metrics, strict=True):
        st = [summary["policies"][p][m] for p in pols]
        means = [s["mean"] or 0.0 for s in st]
        lo = [(s["mean"] - s["ci_low"]) if s["n"] else 0.0 for s in st]
        hi = [(s["ci_high"] - s["mean"]) if s["n"] else 0.0 for s in st]
        ax.bar(pols, means, yerr=[lo, hi], capsize=5, color=[policy_color(p, k) for k, p in enumerate(pols)],
               edgecolor="black", linewidth=0.6)
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("mean per episode")
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    fig.suptitle(f"Violations on {summary['scenes']} {summary['map']} scenes (bars: mean, whiskers: bootstrap 95% CI)",
                 fontsize=11)
    fig.tight_layout()
    return figure_png_base64(fig)


#: knob trajectory panels per row of the report's figure
KNOB_PLOTS_PER_ROW = 5


def fig_knobs(folder: Path, rows: dict[str, list[dict[str, Any]]], knobs: list[str]) -> str | None:
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()
    series: dict[str, np.ndarray] = {}
    for policy, eps in rows.items():
        runs = []
        for e in eps:
            path = steps_path(folder, policy, e["scene"])
            if path.is_file():
                # a knob the campaign's version did not record reads as its default
                steps = [Weather.from_recorded({k: r[k] for k in knobs if k in r})
                         for r in read_steps(path, columns=knobs, steps=e.get("steps"))]
                runs.append(np.array([[w[k] for k in knobs] for w in steps], float).reshape(-1, len(knobs)))
        if runs:
            n = min(len(r) for r in runs)
            series[policy] = np.stack([r[:n] for r in runs])  # (episodes, steps, knobs)
    if not series:
        return None
    cols = min(len(knobs), KNOB_PLOTS_PER_ROW)  # wrapped, so that ten knobs stay readable on a page
    nrows = -(-len(knobs) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.1 * cols, 2.9 * nrows), squeeze=False)
    for ax in axes.flat[len(knobs):]:
        ax.set_visible(False)
    for j, knob in enumerate(knobs):
        ax = axes[j // cols, j % cols]
        for k, (policy, arr) in enumerate(series.items()):
            t = np.arange(arr.shape[1]) * 0.05
            ax.plot(t, arr[:, :, j].mean(axis=0), color=policy_color(policy, k), label=policy, lw=1.6)
            ax.fill_between(t, np.quantile(arr[:, :, j], 0.1, axis=0), np.quantile(arr[:, :, j], 0.9, axis=0),
                            color=policy_color(policy, k), alpha=0.15, lw=0)
        unit = KNOBS[knob].unit if knob in KNOBS else ""
        ax.set_title(knob.replace("_", " ") + (f" [{unit}]" if unit else ""), fontsize=9)
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Knob trajectories: mean over scenes, 10-90% band", fontsize=10)
    fig.tight_layout()
    return figure_png_base64(fig)


#: how the telemetry plot marks the actor events the tester caused
EVENT_STYLE = {"cut_in": ("#d35400", "cut-in begins"), "lead_braking": ("#2980b9", "lead braked by the tester")}


def fig_telemetry(records: list[StepRecord], failure: dict[str, Any], title: str,
                  proximity_m: float | None = None, actor_events: list[dict[str, Any]] | None = None) -> str:
    """Speeds, controls, true and perceived gap, and the hit vehicle's detection timeline around the first
    impact; ``proximity_m``: the proximity rule's threshold to draw, when the rulebook has one;
    ``actor_events``: the episode row's actor events, drawn as dashed lines where they began (in the window)."""
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    hit = next(i for i, r in enumerate(records) if r.collision.collided)
    lo, hi = max(0, hit - 160), min(len(records), hit + 20)
    win = records[lo:hi]
    t = np.array([r.time_s for r in win])
    timeline = detection_timeline(win, failure["vehicle_id"])
    fig, axes = plt.subplots(4, 1, figsize=(7.5, 6.2), sharex=True,
                             gridspec_kw={"height_ratios": [2, 1.4, 2, 0.8]})
    axes[0].plot(t, [r.ego.speed for r in win], color="#c0392b", label="ego speed")
    axes[0].plot(t, [r.lead.speed for r in win], color="#2c3e50", ls="--", label="lead speed")
    axes[0].set_ylabel("m/s")
    axes[1].plot(t, [r.ego.throttle for r in win], color="#27ae60", label="throttle")
    axes[1].plot(t, [r.ego.brake for r in win], color="#8e44ad", label="brake")
    axes[1].set_ylim(-0.05, 1.05)
    axes[2].plot(t, [r.lead.true_distance for r in win], color="#2c3e50", label="true distance to lead")
    axes[2].plot(t, [r.lead.perceived_distance for r in win], ".", ms=3, color="#e67e22",
                 label="perceived distance")
    if proximity_m is not None:
        axes[2].axhline(proximity_m, color="grey", ls=":", lw=1, label=f"proximity threshold {proximity_m:g} m")
    axes[2].set_ylabel("m")
    on = np.array([np.nan if v is None else float(v) for v in timeline])
    axes[3].fill_between(t, 0, np.where(on == 1, 1, 0), step="mid", color="#27ae60", alpha=0.8, lw=0,
                         label="detected")
    axes[3].fill_between(t, 0, np.where(on == 0, 1, 0), step="mid", color="#c0392b", alpha=0.5, lw=0,
                         label="in view, missed")
    axes[3].set_yticks([])
    axes[3].set_xlabel("time [s]")
    shown: set[str] = set()
    for e in actor_events or []:
        color, label = EVENT_STYLE.get(str(e.get("kind")), ("#7f8c8d", str(e.get("kind"))))
        onset = float(e.get("onset_s", -1.0))
        if t.size and t[0] <= onset <= t[-1]:
            for ax in axes:
                ax.axvline(onset, color=color, ls="--", lw=1.0,
                           label=None if label in shown or ax is not axes[0] else label)
            shown.add(label)
    for ax in axes:
        ax.axvline(records[hit].time_s, color="red", lw=1.2)
        ax.legend(fontsize=7, loc="upper left", ncol=3)
        ax.grid(alpha=0.3)
    axes[0].set_title(title, fontsize=10)
    fig.tight_layout()
    return figure_png_base64(fig)


def frame_strip(folder: Path, policy: str, scene: int, records: list[StepRecord], n: int = 6) -> str | None:
    paths = sorted(CampaignFolder(folder).frames(policy, scene).glob("step_*.jpg"))
    if not paths:
        return None
    by_step = {r.step: r for r in records}
    picks = [paths[int(i)] for i in np.linspace(0, len(paths) - 1, min(n, len(paths)))]
    tiles = []
    for p in picks:
        step = int(p.stem.split("_")[1])
        with Image.open(p) as im:
            rgb = np.asarray(im.convert("RGB"))
        tiles.append(annotate_frame(rgb, by_step[step]) if step in by_step else rgb)
    hgt = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, hgt - t.shape[0]), (0, 4), (0, 0)), constant_values=255) for t in tiles]
    return _jpeg(np.hstack(tiles))


def _steps(folder: Path, policy: str, scene: int, steps: int | None = None) -> list[StepRecord]:
    """An episode's step records; ``steps``: the count its row states, which the file must hold exactly."""
    return read_step_records(steps_path(folder, policy, scene), steps)


CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1200px;margin:24px auto;color:#222;
padding:0 16px;line-height:1.45}
h1{font-size:26px;margin-bottom:4px}h2{border-bottom:2px solid #eee;padding-bottom:4px;margin-top:36px}
.meta{color:#666;font-size:13px}.warn{background:#fff3cd;border:1px solid #f0c36d;padding:8px 12px;border-radius:6px}
table{border-collapse:collapse;font-size:13px;margin:8px 0}th,td{border:1px solid #ddd;padding:4px 8px;text-align:right}
th{background:#f6f6f6}td.l,th.l{text-align:left}img{max-width:100%}.card{margin:18px 0 30px}
.good{color:#1e8449;font-weight:600}.bad{color:#c0392b;font-weight:600}.hit{background:#fdecea}
"""


def _fmt_ci(s: dict[str, Any]) -> str:
    if not s["n"] or s["mean"] is None:
        return "–"
    return f"{s['mean']:.2f} <span class=meta>[{s['ci_low']:.2f}, {s['ci_high']:.2f}]</span>"


#: what report writes inside its campaign folder (output_paths): beside the files it reads, never onto them
REPORT_PRODUCTS = (r"report[\w.-]*\.html",)


#: an OpenSCENARIO export's index and folder (openscenario.export.INDEX, SCENARIO_FOLDER: that package replays
#: records through this one, so this one names them instead of importing them)
SCENARIO_INDEX, SCENARIO_FOLDER = "scenarios.json", "scenarios"


def _scenario_index(scenarios: Path | None) -> dict[str, dict[str, Any]]:
    """The export's scenarios by record name; {} without ``--scenarios``."""
    if scenarios is None:
        return {}
    index = scenarios / SCENARIO_INDEX
    if not index.is_file():
        raise UserInputError(f"--scenarios '{scenarios}' holds no {SCENARIO_INDEX}; give the folder of "
                             "`genesis-rl export CAMPAIGN --format openscenario --out DIR`")
    entries = read_json(index, "scenario index").get("scenarios", [])
    return {Path(e["scenario"]).stem: e for e in entries if isinstance(e, dict) and "scenario" in e}


def _scenario_line(folder: Path, record: str, scenarios: Path | None, index: dict[str, dict[str, Any]],
                   report: Path) -> str:
    """The failure's OpenSCENARIO file, linked from the report when the export holds it, else the command that
    writes it."""
    stem = Path(record).stem
    entry = index.get(stem)
    if scenarios is not None and entry is not None and (scenarios / entry["scenario"]).is_file():
        xosc = scenarios / entry["scenario"]
        checked = ""
        if "schema" in entry:
            valid = "valid" if entry["schema"]["valid"] else "INVALID"
            same = "same failure" if entry["replay"]["reproduced"] else "NOT the same failure"
            checked = f" (ASAM schema: {valid}; lite driven from the file: {same})"
        link = os.path.relpath(xosc.resolve(), report.resolve().parent)
        return (f"<p class=meta>OpenSCENARIO: <a href='{html.escape(link)}'>{html.escape(xosc.name)}</a>"
                f"{html.escape(checked)}</p>")
    return (f"<p class=meta>OpenSCENARIO: <code>genesis-rl export {html.escape(str(folder / record))} --format "
            f"openscenario --out scenarios_{html.escape(stem)}</code></p>")


def build_report(folder: Path, out: Path | str | None = None, force: bool = False,
                 max_examples: int = 5, scenarios: Path | None = None, estimate: Path | None = None) -> Path | str:
    """Write ``report.html`` in the campaign folder (or ``out``: a file, or '-' for standard output); returns
    where it went. ``out`` may not be, or lie inside, the campaign (but for ``report*.html``). ``scenarios``: an
    OpenSCENARIO export of the campaign (``export --format openscenario``), whose files the failures link.
    ``estimate``: a ``genesis-rl estimate`` folder of the same system, ODD and map, whose failure rate under
    natural conditions the report states beside the failures found."""
    from genesis_rl.core.files.output_paths import check_inputs, is_stdout, output_file

    folder = Path(folder)
    given = out if out else CampaignFolder(folder).report
    # the report may not land on what it reads: an estimate's files, and what the campaign names (its agent run,
    # catalog, the ODD, rulebook and weights of its env)
    inputs = [folder, estimate, *campaign_named_files(folder)]
    check_inputs(given, inputs, products=REPORT_PRODUCTS)  # before "pass --force", which would not help
    if not is_stdout(given) and Path(given).exists() and not Path(given).is_symlink() and not force:
        raise UserInputError(f"report '{given}' exists; pass --force to rebuild it")
    target = output_file(given, force, inputs=inputs, products=REPORT_PRODUCTS)
    meta, rows = load_campaign(folder)
    rate = None
    if estimate is not None:
        rate = load_estimate(Path(estimate))
        check_same_system(rate, meta["spec"].get("env", {}), meta["spec"].get("map", "highway"))
    scenario_index = _scenario_index(scenarios)
    out = target.path if target.path is not None else Path(str(given))
    if not any(rows.values()):
        raise UserInputError(f"campaign '{folder}' has no finished episodes yet; nothing to report")
    summary = summarize_campaign(folder, write=False, loaded=(meta, rows))
    rulebook = campaign_rulebook(meta, rows)
    _update_summary_files(folder, out, summary, rows, rulebook)
    rule_metrics = rulebook.metric_columns()
    sums = [f"{r.name}_sum" for r in rulebook.rules if not r.in_total]
    spec = meta["spec"]
    knobs = list(spec.get("env", {}).get("knobs") or PAPER_KNOBS)
    unknown = [k for k in knobs if not isinstance(k, str) or k not in KNOBS]
    if unknown:  # a knob of a plug-in this command did not load, or a damaged campaign.json
        raise UserInputError(f"campaign '{folder}': campaign.json spec.env.knobs names {unknown[0]!r}, which is not "
                             f"a knob; allowed: {', '.join(sorted(KNOBS))} (a plug-in's knob: name its module "
                             "in GENESIS_RL_PLUGINS)")
    h: list[str] = [f"<!doctype html><html><head><meta charset=utf-8><title>GENESIS-RL report</title>"
                    f"<style>{CSS}</style></head><body>"]
    h.append("<h1>GENESIS-RL evaluation report</h1>")
    h.append(f"<p class=meta>campaign <code>{html.escape(str(folder))}</code> · map <b>{_esc(summary['map'])}</b> · "
             f"{_esc(summary['scenes'])} scenes (seed {_esc(spec['seed'])}) · {_esc(spec['steps'])} steps each · agent "
             f"<code>{html.escape(str(spec.get('agent')))}</code> · genesis-rl {_esc(meta.get('package_version'))} "
             f"({_esc(str(meta.get('git_commit'))[:10])})</p>")
    if rate is not None:
        h.append(f"<p>{html.escape(estimate_line(rate))}</p>")
    if not summary["complete"]:
        missing = {p: v["missing"] for p, v in summary["policies"].items() if v["missing"]}
        h.append(f"<p class=warn>This campaign is not finished: missing episodes {_esc(missing)}. Figures use the "
                 "finished episodes only; <code>genesis-rl evaluate ... --resume</code> completes it.</p>")

    # 0. natural edge cases (campaigns from 0.6.0 on)
    stated = {(p, e["scene"]): e.get("steps") for p, eps in rows.items() for e in eps}
    h.extend(natural_section(folder, summary, rows, lambda p, sc: _steps(folder, p, sc, stated.get((p, sc))),
                             figure_png_base64,
                             lambda p, sc, recs: frame_strip(folder, p, sc, recs)))
    h.extend(cut_in_html(summary["policies"]))
    cut_fig = fig_cut_ins(rows, {p: policy_color(p, k) for k, p in enumerate(rows)})
    if cut_fig is not None:
        h.append(f"<img src='{figure_png_base64(cut_fig)}'>")

    # 1. comparison
    h.append("<h2>1. Violations by policy (paper Fig. 2)</h2>")
    h.append(f"<img src='{fig_comparison(summary, rulebook)}'>")
    units = {r.name: r.unit for r in rulebook.rules}
    head = [*(f"{m.replace('_', ' ')}" + (f" [{units[m]}]" if units.get(m) else "") for m in rule_metrics),
            *(f"{k[:-4].replace('_', ' ')} summed" for k in sums), "episodes with collision", "mean IoU", "sim steps"]
    h.append("<table><tr><th class=l>policy</th><th>episodes</th>" + "".join(f"<th>{html.escape(c)}</th>" for c in head)
             + "</tr>")
    for p, s in summary["policies"].items():
        cells = [*(_fmt_ci(s[m]) for m in rule_metrics), *(f"{s[k]:.1f}" for k in sums),
                 str(s["episodes_with_collision"]), _fmt_ci(s["mean_iou"]), str(s["sim_steps"])]
        h.append(f"<tr><td class=l>{html.escape(p)}</td><td>{s['episodes']}</td>"
                 + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    h.append("</table>")
    if summary["comparisons"]:
        h.append("<p>Paired comparisons (same scenes, same seeds): mean difference agent − baseline with "
                 "bootstrap 95% CI, scenes where the agent is worse for the ego (wins) / equal / better, and a "
                 "sign-flip permutation p-value.</p><table><tr><th class=l>comparison</th><th class=l>metric</th>"
                 "<th>difference</th><th>wins/ties/losses</th><th>p</th></tr>")
        for name, comp in summary["comparisons"].items():
            for m in rule_metrics:
                c = comp[m]
                d = c["difference"]
                cls = "" if not d["n"] else ("good" if d["ci_low"] > 0 else ("bad" if d["ci_high"] < 0 else ""))
                pv = "–" if c["p_value"] is None else f"{c['p_value']:.3f}"
                h.append(f"<tr><td class=l>{_esc(name)}</td><td class=l>{_esc(m)}</td><td class={cls}>{_fmt_ci(d)}</td>"
                         f"<td>{c['wins']}/{c['ties']}/{c['losses']}</td><td>{pv}</td></tr>")
        h.append("</table>")

    # 2-3. failure modes
    h.append("<h2>2. Failure modes (paper Fig. 3)</h2>")
    counts = "".join(f"<tr><td class=l>{_esc(p)}</td>"
                     + "".join(f"<td>{_esc(s['failure_modes'][m])}</td>" for m in FAILURE_MODES)
                     + "</tr>" for p, s in summary["policies"].items())
    h.append("<table><tr><th class=l>policy</th>" + "".join(f"<th>{MODE_TITLES[m]}</th>" for m in FAILURE_MODES)
             + f"</tr>{counts}</table>")
    h.append("<p class=meta>Labels come from the detection timeline of the hit vehicle in the 4 s before the "
             "impact (thresholds in summary.json and docs/evaluation.md).</p>")
    preferred = ("agent", "cmaes", "cem", "constant", "random", "sunny")
    order = [p for p in preferred if p in rows] + [p for p in rows if p not in preferred]
    shown = 0
    for mode in FAILURE_MODES:
        example = next(((p, e) for p in order for e in rows[p] if e["failure_mode"] == mode), None)
        if example is None or shown >= max_examples:
            continue
        shown += 1
        p, e = example
        recs = _steps(folder, p, e["scene"], e.get("steps"))
        title = (f"{MODE_TITLES[mode]}: {p}, scene {e['scene']}, impact at {e['failure']['speed']:.1f} m/s, "
                 f"step {e['first_collision_step']}")
        proximity = rulebook.rule("proximity")
        fig = fig_telemetry(recs, e["failure"], title, getattr(proximity, "distance", None), e.get("actor_events"))
        h.append(f"<div class=card><h3>{html.escape(title)}</h3><img src='{fig}'>")
        strip = frame_strip(folder, p, e["scene"], recs)
        if strip:
            h.append(f"<p class=meta>Camera before the impact (green: true boxes, orange: detections):</p>"
                     f"<img src='{strip}'>")
        if e.get("record"):
            h.append(f"<p class=meta>Replay: <code>genesis-rl replay {html.escape(str(folder / e['record']))} "
                     f"--out replay_{_esc(p)}_{_esc(e['scene'])}</code></p>")
            h.append(_scenario_line(folder, e["record"], scenarios, scenario_index, out))
        h.append("</div>")
    if shown == 0:
        h.append("<p>No collisions in this campaign.</p>")

    # 4. knobs
    h.append("<h2>3. Knob trajectories</h2>")
    knob_fig = fig_knobs(folder, rows, knobs)
    if knob_fig:
        h.append(f"<img src='{knob_fig}'>")

    # training curve of the agent, when its run folder is at hand
    if spec.get("agent"):
        curve = agent_learning_curve(Path(spec["agent"]))
        if curve is not None:
            h.append(f"<h2>Training of the agent</h2><img src='{figure_png_base64(curve)}'>")

    # 5. per-scene table
    counted = [r.name for r in rulebook.rules if r.in_total]
    h.append(f"<h2>4. Per scene</h2><p class=meta>{' / '.join(counted)} violation; red: a collision, with its "
             "failure mode.</p><table><tr><th class=l>scene</th>" + "".join(f"<th>{_esc(p)}</th>" for p in rows)
             + "</tr>")
    by_scene = {p: {e["scene"]: e for e in eps} for p, eps in rows.items()}
    for scene, _ in meta["scenes"]:
        cells = []
        for p in rows:
            ep = by_scene[p].get(scene)
            if ep is None:
                cells.append("<td class=meta>missing</td>")
                continue
            mode = f"<br><span class=meta>{_esc(ep['failure_mode'])}</span>" if ep["failure_mode"] else ""
            scores = " / ".join(f"{ep[m]:.1f}" for m in counted)
            cells.append(f"<td class={'hit' if ep['collision_events'] else ''}>{scores}{mode}</td>")
        h.append(f"<tr><td class=l>{_esc(scene)}</td>{''.join(cells)}</tr>")
    h.append("</table>")
    h.append(f"<h2>Campaign settings</h2><pre>{html.escape(json.dumps(spec, indent=1))}</pre></body></html>")
    try:
        target.write_text("\n".join(h))
    except OSError as err:
        message = os_error_message(err, hint=False)
        if message is None or target.path is None or out.parent.resolve() != folder.resolve():
            raise
        raise UserInputError(f"{message}; pass --out FILE to write the report elsewhere") from None
    return out if target.path is not None else str(target)


def _update_summary_files(folder: Path, out: Path, summary: dict[str, Any], rows: dict[str, list[dict[str, Any]]],
                          rulebook: Rulebook) -> None:
    """Bring the campaign's ``summary.json`` and ``episodes.csv`` up to date (written only when changed). When
    the campaign folder cannot be written (read-only, no permission, full) and the report goes elsewhere,
    say so and go on: the report is built from the episodes as they are."""
    try:
        write_summary_files(folder, summary, rows, rulebook)
    except OSError as err:
        message = os_error_message(err, hint=False)
        if message is None:
            raise
        if out.parent.resolve() == folder.resolve():
            raise UserInputError(f"{message}; pass --out FILE to write the report elsewhere") from None
        print(f"genesis-rl report: note: summary.json and episodes.csv of '{folder}' not updated ({message}); the "
              "report is built from its episode files as they are", file=sys.stderr)
