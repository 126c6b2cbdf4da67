"""Issue 17 item 5: an agent evaluated against a system under test it never trained with (``evaluate --system``
and ``--weights``), and the errors that name a wrong pairing."""

from __future__ import annotations

import json
import shutil

from genesis_rl.commands.cli import main
from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS


def test_evaluate_swaps_the_detector_weights_and_records_them(tmp_path, capsys) -> None:
    weights = tmp_path / "other_detector.pt"
    shutil.copy(DEFAULT_WEIGHTS, weights)
    out = tmp_path / "eval"
    assert main(["evaluate", "--policies", "sunny", "--scenes", "1", "--steps", "6", "--weights", str(weights),
                 "--no-report", "--quiet", "--out", str(out)]) == 0
    capsys.readouterr()
    campaign = json.loads((out / "campaign.json").read_text())
    assert campaign["spec"]["env"]["system_kwargs"] == {"weights": str(weights)}
    # the identity a resume checks names the file the episodes ran with, not the shipped one
    assert campaign["identity"]["system"]["weights"] == str(weights)

def test_weights_for_a_system_without_a_detector_are_refused(tmp_path, capsys) -> None:
    out = tmp_path / "eval"
    assert main(["evaluate", "--policies", "sunny", "--scenes", "1", "--steps", "6", "--system", "oracle",
                 "--weights", str(DEFAULT_WEIGHTS), "--no-report", "--quiet", "--out", str(out)]) == 2
    refusal = "--weights applies to --system builtin, yolo, coco, latency, adaptive, stall only, not 'oracle'"
    assert refusal in capsys.readouterr().err
    assert main(["evaluate", "--policies", "sunny", "--scenes", "1", "--steps", "6",
                 "--weights", str(tmp_path / "missing.pt"), "--no-report", "--quiet", "--out", str(out)]) == 2
    assert "missing.pt' is not a file" in capsys.readouterr().err
    assert not out.exists()
