"""A shared campaign's strings are data at every boundary: HTML (report.html), CSV (episodes.csv opened in a
spreadsheet), matplotlib text (figure titles and legends) and XML (OpenSCENARIO). Each test edits a campaign
written by 0.29.0 the way a hostile colleague could, then checks what reaches the output."""

from __future__ import annotations

import json
import os
import xml.dom.minidom
from pathlib import Path

import pytest

from genesis_rl.commands.cli import main

IMG = "<img src=x onerror=alert(1)>"


@pytest.fixture()
def camp(v029: Path) -> Path:
    return v029 / "camp"


def _rename_policy(camp: Path, old: str, new: str) -> None:
    meta = json.loads((camp / "campaign.json").read_text())
    meta["spec"]["policies"] = [new if p == old else p for p in meta["spec"]["policies"]]
    (camp / "campaign.json").write_text(json.dumps(meta))
    for sub in ("episodes", "steps"):
        os.rename(camp / sub / old, camp / sub / new)
    for f in (camp / "episodes" / new).iterdir():
        ep = json.loads(f.read_text())
        ep["policy"] = new
        f.write_text(json.dumps(ep))


def _edit_episode(camp: Path, policy: str, scene: str, **fields: object) -> None:
    path = camp / "episodes" / policy / f"{scene}.json"
    ep = json.loads(path.read_text())
    ep.update(fields)
    path.write_text(json.dumps(ep))


@pytest.mark.parametrize("name", [IMG, "$\\undefinedcmd$", "<b>x<b>&amp;"])
def test_a_hostile_policy_name_reaches_report_html_as_text(camp: Path, name: str) -> None:
    _rename_policy(camp, "random", name)
    assert main(["report", str(camp), "--force"]) == 0  # mathtext in a legend had ended here in a traceback
    page = (camp / "report.html").read_text()
    assert "<img src=x" not in page and "<b>x<b>" not in page
    if name == IMG:
        assert page.count("&lt;img src=x onerror=alert(1)&gt;") >= 3  # tables, per-scene header, settings


def test_a_hostile_failure_mode_is_escaped_and_no_cell_runs_as_a_formula(camp: Path) -> None:
    _edit_episode(camp, "agent", "scene_0001", failure_mode="<script>alert(1)</script>", collision_events=1)
    _edit_episode(camp, "random", "scene_0002", failure_mode='=HYPERLINK("http://x","y")')
    _rename_policy(camp, "random", "@SUM(1+1)")
    assert main(["report", str(camp), "--force"]) == 0
    page = (camp / "report.html").read_text()
    assert "<script>" not in page and "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    cells = [c for line in (camp / "episodes.csv").read_text().splitlines() for c in line.split(",")]
    assert not [c for c in cells if c.lstrip('"').startswith(("=", "+", "@", "\t", "\r"))]
    assert any(c.startswith("\"'=HYPERLINK") for c in cells) and "'@SUM(1+1)" in cells


def test_safe_cell_leaves_numbers_and_plain_text_alone() -> None:
    from genesis_rl.core.files.spreadsheet import safe_cell

    assert [safe_cell(v) for v in (-1.5, 0, "agent", "-1", "-1e3", "-1+1", "=1+1", "\tx")] == \
        [-1.5, 0, "agent", "-1", "-1e3", "'-1+1", "'=1+1", "'\tx"]


def test_a_control_character_in_a_record_gives_a_well_formed_xosc(camp: Path, tmp_path: Path) -> None:
    pytest.importorskip("scenariogeneration")
    record = camp / "records" / "agent_scene_0001.json"
    rec = json.loads(record.read_text())
    rec["policy"] = "agent\x01\x1b[31m"
    record.write_text(json.dumps(rec))
    out = tmp_path / "xosc"
    assert main(["export", str(record), "--format", "openscenario", "--no-check", "--out", str(out), "--quiet"]) == 0
    files = list(out.rglob("*.xosc"))
    assert files
    for f in files:
        text = f.read_text(encoding="utf-8")
        xml.dom.minidom.parseString(text)  # well-formed, or this raises
        assert "\x01" not in text and "\x1b" not in text and "agent\ufffd\ufffd[31m" in text


def test_a_log_axis_is_labelled_with_plain_numbers_when_text_is_not_math() -> None:
    """With mathtext off, a log axis's default labels showed their source ($\\mathdefault{10^{3}}$) in the
    report's ODD coverage figure."""
    from genesis_rl.core.plotting import plain_log_ticks, pyplot

    plt = pyplot()
    fig, ax = plt.subplots()
    ax.set_xscale("log")
    ax.set_xlim(8, 4000)
    plain_log_ticks(ax.xaxis)
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
    plt.close(fig)
    assert {"10", "100", "1000"} <= set(labels) and not any("$" in t for t in labels)
