"""The built-in vehicle detector: targets/decoding, weights loading, the protocol, and the shipped weights'
accuracy on held-out urban frames (competent in clear daylight, brittle in dense fog and at night)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch

from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS, NullDetector, VehicleDetector, load_checkpoint
from genesis_rl.sut.perception.evaluate import EVAL_CATALOG_SEEDS, EvalProtocol, match_frame, score_dataset
from genesis_rl.sut.perception.model import (
    DetectorModelConfig,
    VehicleDetectorNet,
    box_iou,
    decode,
    encode_targets,
)


def _targets_as_outputs(t: dict) -> dict:
    heat = torch.from_numpy(t["heatmap"][None]).clamp(1e-6, 1 - 1e-6)
    return {"heatmap": torch.logit(heat), "size": torch.from_numpy(t["size"][None]),
            "offset": torch.from_numpy(t["offset"][None])}


def test_encode_decode_round_trip() -> None:
    rng = np.random.default_rng(0)
    boxes = []
    for cx, cy in ((40, 60), (120, 150), (200, 100), (290, 200), (160, 40), (70, 210)):
        w, h = rng.uniform(6, 90, 2)
        boxes.append([cx + rng.uniform(-2, 2) - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])
    boxes = np.array(boxes)
    t = encode_targets(boxes, 60, 80, 4)
    assert t["heatmap"].shape == (1, 60, 80) and t["reg_mask"].sum() == len(boxes)
    dets = decode(_targets_as_outputs(t), score_threshold=0.99, max_detections=20)[0]
    assert dets.shape == (len(boxes), 5) and dets.dtype == np.float32
    iou = box_iou(boxes, dets)
    j = iou.argmax(axis=1)
    assert len(set(j.tolist())) == len(boxes)
    np.testing.assert_allclose(dets[j, :4], boxes, atol=1.0)


def test_encode_ignore_regions_and_clipping() -> None:
    t = encode_targets(np.array([[300.0, 200.0, 330.0, 250.0]]), 60, 80, 4, ignore=np.array([[0, 0, 40, 20]]))
    assert t["hm_weight"][0, :5, :10].max() == 0.0 and t["hm_weight"][0, 30, 30] == 1.0
    assert t["reg_mask"].sum() == 1  # a box centre past the border lands on the last cell
    empty = decode(_targets_as_outputs(encode_targets(np.zeros((0, 4)), 60, 80)), 0.5, 10)[0]
    assert empty.shape == (0, 5)


def test_network_shapes() -> None:
    cfg = DetectorModelConfig()
    out = VehicleDetectorNet(cfg).eval()(torch.zeros(2, 3, cfg.input_height, cfg.input_width))
    assert out["heatmap"].shape == (2, 1, 60, 80) and out["size"].shape == (2, 2, 60, 80)
    assert torch.sigmoid(out["heatmap"]).mean().item() == pytest.approx(0.1, abs=0.05)
    with pytest.raises(ValueError, match="multiple"):
        DetectorModelConfig(input_width=300)


def test_missing_and_corrupt_weights(tmp_path) -> None:
    missing = tmp_path / "nope.pt"
    with pytest.raises(UserInputError, match="nope.pt"):
        VehicleDetector(missing)
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"\x00not a checkpoint" * 10)
    with pytest.raises(UserInputError, match=r"corrupt\.pt is not a genesis-rl detector checkpoint"):
        VehicleDetector(corrupt)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(UserInputError, match=r"foreign\.pt is not a genesis-rl detector checkpoint"):
        VehicleDetector(foreign)
    ckpt = load_checkpoint(DEFAULT_WEIGHTS)
    ckpt["model_config"] = {**ckpt["model_config"], "channels": [8, 8, 8, 8, 8]}
    mismatched = tmp_path / "mismatched.pt"
    torch.save(ckpt, mismatched)
    with pytest.raises(UserInputError, match=r"mismatched\.pt does not match"):
        VehicleDetector(mismatched)


def test_null_detector() -> None:
    det = NullDetector()
    frame = np.zeros((240, 320, 3), np.uint8)
    out = det.detect(frame)
    assert out.shape == (0, 5) and out.dtype == np.float32
    batch = det.detect_batch(np.zeros((3, 240, 320, 3), np.uint8))
    assert len(batch) == 3 and all(b.shape == (0, 5) for b in batch)
    with pytest.raises(ValueError):
        det.detect(np.zeros((240, 320), np.uint8))


def test_shipped_weights_load() -> None:
    det = VehicleDetector()
    assert 0.0 < det.score_threshold < 1.0 and det.input_size == (320, 240)
    assert len(det.weights_sha256) == 64
    assert DEFAULT_WEIGHTS.stat().st_size < 2_000_000
    assert DEFAULT_WEIGHTS.with_suffix(".json").is_file()
    assert det.detect(np.zeros((240, 320, 3), np.uint8)).shape[1] == 5


def test_folded_batch_norm_computes_the_same_net() -> None:
    """The inference net folds each BatchNorm into its conv; its outputs equal the trained net's."""
    det = VehicleDetector()
    ckpt = load_checkpoint(DEFAULT_WEIGHTS)
    net = VehicleDetectorNet(DetectorModelConfig.from_dict(dict(ckpt["model_config"])))
    net.load_state_dict(ckpt["state_dict"])
    net.eval()
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in det._net.modules())
    x = torch.rand(2, 3, 240, 320, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        a, b = net(x), det._net(x.contiguous(memory_format=torch.channels_last))
    for key in ("heatmap", "size", "offset"):
        assert torch.allclose(a[key], b[key], atol=1e-4), key


def _gt(*rows) -> np.ndarray:
    """Ground-truth rows (frame, x0, y0, x1, y1, distance, visible_fraction, truncated, id)."""
    return np.array([[0, *r[:4], r[4], r[5], 0, i] for i, r in enumerate(rows)], np.float32).reshape(-1, 9)


def test_protocol_matching() -> None:
    gt = _gt((10, 10, 50, 50, 20.0, 1.0), (100, 100, 140, 140, 80.0, 1.0), (200, 100, 204, 104, 10.0, 1.0))
    dets = np.array([
        [11, 11, 50, 50, 0.9],  # TP
        [10, 10, 49, 51, 0.8],  # duplicate of a matched vehicle: FP
        [100, 100, 141, 140, 0.7],  # a far vehicle (ignore region): neither
        [250, 10, 290, 50, 0.6],  # nothing there: FP
    ], np.float32)
    m = match_frame(dets, gt)
    assert (m.tp, m.fp, m.fn, m.ignored) == (1, 2, 0, 1)
    assert m.mean_iou > 0.9
    assert match_frame(np.zeros((0, 5)), gt).fn == 1
    assert EvalProtocol().counted(gt).tolist() == [True, False, False]


def test_detector_commands_bad_input(tmp_path) -> None:
    from genesis_rl.commands.detector import add_parser as add_detector_command

    p = argparse.ArgumentParser()
    add_detector_command(p.add_subparsers(dest="command"))
    args = p.parse_args(["detector", "eval", "--maps", "moon", "--out", str(tmp_path)])
    with pytest.raises(UserInputError, match=r"--maps.*allowed: urban, highway"):
        args.func(args)
    args = p.parse_args(["detector", "eval", "--conditions", "snow", "--out", str(tmp_path)])
    with pytest.raises(UserInputError, match=r"--conditions.*fog90"):
        args.func(args)
    with pytest.raises(UserInputError, match="--frames = 0; allowed: an integer >= 1"):  # as it is parsed
        p.parse_args(["detector", "train", "--frames", "0", "--out", str(tmp_path)])


# ---------------------------------------------------------------------------------------------- rendered
@pytest.fixture(scope="module")
def held_out_sets():
    pytest.importorskip("panda3d")
    from genesis_rl.sut.perception.dataset import render_condition_sets

    return render_condition_sets("urban", 12, 2, EVAL_CATALOG_SEEDS["urban"], seed=11,
                                 conditions=("clear", "fog90", "night"), progress=False)


@pytest.mark.render
def test_shipped_detector_clear_vs_fog_and_night(held_out_sets) -> None:
    torch.set_num_threads(2)
    det = VehicleDetector()
    res = {c: score_dataset(det.detect_batch(d.images), d) for c, d in held_out_sets.items()}
    clear = res["clear"]
    assert clear.tp + clear.fn >= 30, "too few counted vehicles for a meaningful check"
    assert clear.recall >= 0.9 and clear.precision >= 0.9, (clear.recall, clear.precision)
    assert res["fog90"].recall <= clear.recall - 0.25, res["fog90"].recall
    assert res["night"].recall <= clear.recall - 0.25, res["night"].recall


@pytest.mark.render
def test_fast_input_path_is_bit_identical(held_out_sets) -> None:
    """The closed loop's detector path (a table look-up for /255 and the normalisation, a TorchScript trace of
    the net) gives the eager net's outputs on x / 255 bit for bit, single frames and batches alike: the
    system under test is the same whatever the speed-ups (docs/benchmarks.md)."""
    det = VehicleDetector()
    frames = np.stack([f for d in held_out_sets.values() for f in d.images[:6]])
    with torch.inference_mode():
        for batch in (1, 4):
            for s in range(0, len(frames) - batch + 1, batch):
                chunk = frames[s : s + batch]
                x = torch.from_numpy(chunk).permute(0, 3, 1, 2).float().div_(255.0)
                eager = det._net(x.contiguous(memory_format=torch.channels_last))
                fast = det._forward(torch.from_numpy(det._normalized(chunk)).permute(0, 3, 1, 2))
                for key in ("heatmap", "size", "offset"):
                    assert torch.equal(eager[key], fast[key]), (batch, s, key)
    assert len(det._traced) == 2  # one trace per input shape, reused


@pytest.mark.render
def test_detector_rescales_other_frame_sizes(held_out_sets) -> None:
    import cv2

    det = VehicleDetector()
    frame = held_out_sets["clear"].images[0]
    small = det.detect(frame)
    big = det.detect(cv2.resize(frame, (640, 480), interpolation=cv2.INTER_LINEAR))
    assert len(small) > 0 and abs(len(big) - len(small)) <= 1
    iou = box_iou(small * np.array([2, 2, 2, 2, 1]), big)
    assert (iou.max(axis=1) > 0.7).mean() >= 0.8


@pytest.mark.render
def test_dataset_deterministic_and_saved(tmp_path) -> None:
    pytest.importorskip("panda3d")
    from genesis_rl.sut.perception.dataset import DetectionDataset, render_dataset

    a = render_dataset("highway", 2, 1, 5, seed=3, condition="low_sun_glare", progress=False)
    b = render_dataset("highway", 2, 1, 5, seed=3, condition="low_sun_glare", progress=False)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.weather, b.weather)
    path = tmp_path / "d.npz"
    a.save(path)
    c = DetectionDataset.load(path)
    np.testing.assert_array_equal(c.images, a.images)
    assert c.meta["condition"] == "low_sun_glare" and len(c) == 2
    with pytest.raises(UserInputError, match="nothing.npz"):
        DetectionDataset.load(tmp_path / "nothing.npz")
