"""The real-photo system's built-in retrain (``harden --retrain builtin`` on ``coco``): the darknet model it writes
loads as the coco system and darknet's own format, the YOLOv3 loss falls as it trains, the frozen layers stay as
they were, and the same request gives the same bytes (a resumed round is checked by its hash)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.harden.data import original_frames
from genesis_rl.harden.retrain import RetrainRequest, builtin_hook, check_options
from genesis_rl.harden.retrain_darknet import (
    WEIGHTS_NAME,
    _input,
    _targets,
    finetune_darknet,
    folded_cfg,
    weights_bytes,
    yolo_loss,
)
from genesis_rl.sut.perception.coco_detector import CocoDetector, weights_cfg
from genesis_rl.sut.perception.model_store import find_model

pytestmark = pytest.mark.xdist_group("harden_darknet")


def _recipe(seed: int) -> dict:
    return {"map": "highway", "condition": "clear", "train_catalog_seed": seed, "seed": 0, "frames_per_scene": 4}


@pytest.fixture(scope="module")
def failures(tmp_path_factory) -> Path:
    """A failure export made by hand: 6 rendered highway frames with their simulator boxes, in export's layout."""
    from PIL import Image

    data = original_frames(_recipe(57), 6, None)
    out = tmp_path_factory.mktemp("darknet") / "failures"
    (out / "images").mkdir(parents=True)
    lines = []
    for i in range(len(data)):
        Image.fromarray(data.images[i]).save(out / "images" / f"f{i}.jpg", quality=92)
        rows = data.frame_boxes(i)
        labels = [{"xyxy": [float(v) for v in r[1:5]], "distance_m": float(r[5]), "visible_fraction": float(r[6]),
                   "vehicle_id": int(r[8])} for r in rows]
        lines.append(json.dumps({"image": f"images/f{i}.jpg", "labels": labels, "ignore": [], "weather": {}}))
    (out / "metadata.jsonl").write_text("\n".join(lines) + "\n")
    return out


def _request(failures: Path, out: Path, **options) -> RetrainRequest:
    opts = {"epochs": 1, "original_frames": 2, "failure_repeat": 1, "batch_size": 4, **options}
    return RetrainRequest(round=1, system="coco", weights=find_model("coco")["yolov3-tiny.weights"].parent,
                          failures=(failures,), out=out / "weights", seed=0, work=out, options=opts, map="highway")


def test_a_folded_model_folder_reloads_to_the_same_detections(tmp_path) -> None:
    base = CocoDetector()
    cfg = base.folder / "yolov3-tiny.cfg"
    (tmp_path / "yolov3-tiny.cfg").write_text(folded_cfg(weights_cfg(cfg.read_text(), str(cfg))))
    (tmp_path / WEIGHTS_NAME).write_bytes(weights_bytes(base.net))
    (tmp_path / "coco.names").write_bytes((base.folder / "coco.names").read_bytes())
    frames = original_frames(_recipe(58), 4, None).images
    again = CocoDetector(tmp_path)
    for a, b in zip(base.detect_batch(frames), again.detect_batch(frames), strict=True):
        assert a.shape == b.shape and np.array_equal(a, b)
    assert sum(len(a) for a in base.detect_batch(frames)) > 0


def test_the_yolo_loss_falls_on_the_frames_it_trains_on(failures: Path) -> None:
    import torch

    from genesis_rl.harden.data import export_frames

    torch.manual_seed(0)
    det = CocoDetector()
    data = export_frames(failures)
    idx = np.arange(4)
    x, scale, hw = _input(data.images[idx], det.image_size)
    boxes, ignores = _targets(data, idx, scale, np.zeros(4, bool), data.images.shape[2])
    assert sum(len(b) for b in boxes) >= 4
    params = [p for i, layer in enumerate(det.net.layers) if i >= 8 for p in layer.parameters()]
    opt = torch.optim.Adam(params, lr=1e-4)  # the default; 1e-3 overshoots from the pretrained weights
    det.net.train()
    losses = []
    for _ in range(4):
        loss = yolo_loss(det.net, det.net(x, frozen=8), boxes, ignores, hw, det.class_ids)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.8 * losses[0]


def test_the_coco_finetune_writes_a_loadable_model_the_same_bytes_twice(failures: Path, tmp_path) -> None:
    from genesis_rl.sut.system.protocol import load_system

    first = builtin_hook(_request(failures, tmp_path / "a"))  # dispatches to the darknet fine-tune by system
    second = finetune_darknet(_request(failures, tmp_path / "b"))
    assert (first / WEIGHTS_NAME).read_bytes() == (second / WEIGHTS_NAME).read_bytes()
    record = json.loads((first / "finetune.json").read_text())
    assert record["failure_frames"] == 6 and record["original_frames"] == 2 and len(record["failure_sha256"]) == 64
    system = load_system("coco", weights=str(first))
    base, tuned = CocoDetector().net, system.detector.net
    convs = [i for i, k in enumerate(base.kinds) if k == "convolutional"]
    moved = {i: float((base._conv(i).weight - tuned._conv(i).weight).detach().abs().max()) for i in convs}
    assert all(moved[i] == 0.0 for i in convs if i < 8)  # the frozen feature extractor
    assert sum(moved[i] > 0 for i in convs if i >= 8) >= 5


def test_settings_of_the_other_finetune_are_refused_by_name(failures: Path, tmp_path) -> None:
    with pytest.raises(UserInputError, match="validation_frames"):
        finetune_darknet(_request(failures, tmp_path, validation_frames=10))
    with pytest.raises(UserInputError, match="freeze"):
        check_options({"freeze": -1})
    with pytest.raises(UserInputError, match="unknown setting"):
        check_options({"nonsense": 1})
    check_options({"freeze": 4, "epochs": 2})
