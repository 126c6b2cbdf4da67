"""genesis-rl realism: the scoring rules (on a fake detector whose answers are known) and the command's outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.commands.cli import main
from genesis_rl.sut.perception import realism

SPEC = realism.RealismSpec(maps=("highway",), sizes=((320, 240),), scenes=6, frames_per_scene=1)


@pytest.fixture(scope="module")
def views():
    return realism.render_views(SPEC, "highway", (320, 240))


def test_recall_by_band_and_false_positives_follow_the_rules(views) -> None:
    """A fake detector that returns the true box of every vehicle nearer than 20 m, a box shrunk to IoU ~0.4
    for 20-30 m, and one box in the sky per frame."""

    def detect_batch(images: np.ndarray) -> list[np.ndarray]:
        out = []
        for i in range(len(images)):
            rows = []
            for g in views.frame_boxes(i):
                x0, y0, x1, y1 = g[1:5]
                if g[5] < 20:
                    rows.append([x0, y0, x1, y1, 0.9])
                elif g[5] < 30:  # the middle 63 % of each side: IoU 0.4, found only by the loose rule
                    dx, dy = (x1 - x0) * 0.185, (y1 - y0) * 0.185
                    rows.append([x0 + dx, y0 + dy, x1 - dx, y1 - dy, 0.9])
            rows.append([2, 2, 12, 12, 0.5])  # the sky's top-left corner: no vehicle there
            out.append(np.asarray(rows, np.float32).reshape(-1, 5))
        return out

    score = realism.score_views(detect_batch, views, SPEC, "highway").as_dict()
    bands = score["recall_by_distance"]
    assert bands["0-10 m"]["counted"] + bands["10-20 m"]["counted"] >= 3
    for name in ("0-10 m", "10-20 m"):
        if bands[name]["counted"]:
            assert bands[name]["recall"] == 1.0
    if bands["20-30 m"]["counted"]:
        assert bands["20-30 m"]["recall"] == 0.0 and bands["20-30 m"]["recall_loose"] == 1.0
    assert bands["30-40 m"]["found_loose"] == 0
    assert score["within_20m"]["recall"] == 1.0
    assert score["false_positives_per_frame"] == 1.0  # the sky box, and no true box is ever called false
    # occluded or edge-cut vehicles are not counted
    gt = views.boxes
    counted = ((gt[:, 6] >= SPEC.min_visible) & (gt[:, 7] <= 0.5) & (gt[:, 5] < 40)).sum()
    assert sum(b["counted"] for b in bands.values()) == counted


def test_realism_command_writes_json_and_sheet(tmp_path: Path, capsys) -> None:
    out = tmp_path / "realism"
    rc = main(["realism", "--system", "builtin", "--maps", "highway", "--sizes", "320x240", "--scenes", "4",
               "--frames-per-scene", "1", "--closed-loop-scenes", "1", "--closed-loop-steps", "40", "--workers", "1",
               "--out", str(out), "--quiet"])
    assert rc == 0
    data = json.loads((out / "realism.json").read_text())
    assert data["schema"] == "genesis-rl/realism" and data["system"]["class"].endswith("BuiltinSystem")
    (view,) = data["views"]
    assert view["size"] == "320x240" and view["frames"] == 4
    for band in view["recall_by_distance"].values():
        assert 0 <= band["found"] <= band["found_loose"] <= band["counted"]
    assert data["closed_loop"]["scenes"] == 1 and data["closed_loop"]["steps"] == 40
    assert (out / "closed_loop" / "summary.json").is_file()
    from PIL import Image

    with Image.open(out / "realism_sheet_highway.png") as sheet:
        assert sheet.width > 1000 and sheet.height > 500
    capsys.readouterr()
    assert main(["realism", "--out", str(out), "--maps", "highway", "--closed-loop-scenes", "0"]) == 2
    assert "exists" in capsys.readouterr().err


def test_realism_refuses_bad_flags(tmp_path: Path, capsys) -> None:
    for flags, words in ((["--sizes", "320by240"], "WIDTHxHEIGHT"), (["--maps", "moon"], "allowed: "),
                         (["--scenes", "0"], "--scenes = 0 must be in 1..500"),
                         (["--system", "blind"], "has no detector to score")):
        assert main(["realism", "--out", str(tmp_path / "r"), "--closed-loop-scenes", "0", *flags]) == 2
        assert words in capsys.readouterr().err
