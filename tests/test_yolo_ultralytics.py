"""The YOLO adapter against the real ultralytics package (extra ``yolo``; skipped where it is not installed).

No weights are downloaded: nets are built from ultralytics' bundled yolov5n config and saved to local
files, which is what the adapter is given. Their class biases are set so that one net sees a car
everywhere and another a person everywhere: the adapter must keep the first's boxes and drop the
second's. Run with: ``pip install -e '.[yolo]' && pytest tests/test_yolo_ultralytics.py``.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

ultralytics = pytest.importorskip("ultralytics")
torch = pytest.importorskip("torch")

COCO_CAR, COCO_PERSON = 2, 0


def _biased_net(path, coco_class: int) -> str:
    os.environ["YOLO_OFFLINE"] = "true"
    model = ultralytics.YOLO("yolov5n.yaml")  # bundled architecture, random weights
    with torch.no_grad():
        for branch in model.model.model[-1].cv3:  # per-scale class branches of the Detect head
            branch[-1].bias.fill_(-10.0)
            branch[-1].bias[coco_class] = 10.0
    model.save(str(path))
    return str(path)


@pytest.fixture(scope="module")
def nets(tmp_path_factory) -> dict[str, str]:
    folder = tmp_path_factory.mktemp("yolo")
    return {"car": _biased_net(folder / "car.pt", COCO_CAR), "person": _biased_net(folder / "person.pt", COCO_PERSON)}


def _frame():
    from genesis_rl.sim.interface import SensorFrame

    rgb = np.random.default_rng(0).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    return SensorFrame(step=0, rgb=rgb, depth=np.full((240, 320), 20.0, np.float32), boxes=[])


def test_yolo_keeps_vehicle_classes_as_xyxy_score_rows(nets) -> None:
    from genesis_rl.sut.system.protocol import load_system

    frame = _frame()
    cars = load_system("yolo", weights=nets["car"], image_size=320)._boxes(frame)
    assert cars.shape[1] == 5 and len(cars) > 10
    assert np.all(cars[:, 2] > cars[:, 0]) and np.all(cars[:, 3] > cars[:, 1])
    assert np.all((cars[:, [0, 2]] >= 0) & (cars[:, [0, 2]] <= 320)) and np.all(cars[:, [1, 3]] <= 240)
    assert np.all(cars[:, 4] > 0.99)
    people = load_system("yolo", weights=nets["person"], image_size=320)._boxes(frame)
    assert people.shape == (0, 5)  # persons are not vehicles
    assert os.environ["YOLO_OFFLINE"].lower() == "true"


def test_yolo_system_drives_a_closed_loop_episode(nets, tmp_path) -> None:
    from genesis_rl.commands.cli import main

    out = tmp_path / "drive"
    rc = main(["drive", "--map", "highway", "--scene", "3", "--weather", "clear_noon", "--steps", "20",
               "--system", "yolo", "--weights", nets["car"], "--out", str(out), "--no-gif", "--quiet"])
    assert rc == 0
    assert (out / "telemetry.parquet").is_file() and (out / "summary.json").is_file()
