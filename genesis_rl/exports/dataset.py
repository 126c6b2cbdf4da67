"""Export the failure windows of a campaign as a detector training set (YOLO or COCO).

Frames are the camera images a campaign kept around each first collision (``frames/``); labels are the
simulator's ground-truth boxes at those steps (``steps/*.parquet``), clipped to the image. A vehicle counts
as a label when at least ``MIN_VISIBLE`` of it is unoccluded and its box is ``MIN_HEIGHT`` px tall (a
little stricter than the detector's training rule: 20 % visible, 5 px tall, 4 px wide); smaller or hidden
ones are listed as ignore regions (COCO ``iscrowd = 1``; YOLO has no ignore syntax, so they go to
``metadata.jsonl`` only). Every image carries its weather knobs, scene, policy, step and the failure mode
of its episode, so a perception team can slice by condition.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from PIL import Image

from genesis_rl.campaigns.campaign_files import REMEDY, episode_path, read_episode_row, read_steps, steps_path
from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.campaigns.summary import load_campaign
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write_json, atomic_write_text, remove_tree
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.step_record import RecordedBox

FORMATS = ("yolo", "coco")
CLASSES = ("vehicle",)
MIN_VISIBLE = 0.3
MIN_HEIGHT = 5.0  # [px]


def _frames(folder: Path) -> list[tuple[str, int, int, Path]]:
    """(policy, scene, step, path) of every kept frame."""
    out = []
    for path in sorted(CampaignFolder(folder).frames_dir.glob("*/scene_*/step_*.jpg")):
        policy = path.parent.parent.name
        scene = int(path.parent.name.split("_")[1])
        step = int(path.stem.split("_")[1])
        out.append((policy, scene, step, path))
    return out


def export_dataset(folder: Path, fmt: str, out: Path, force: bool = False,
                   policies: list[str] | None = None,
                   add_to_export: Callable[[Path], dict[str, Any]] | None = None,
                   keep: Callable[[str, int, int], bool] | None = None,
                   extra_frames: Path | None = None) -> dict[str, Any]:
    """The failure frames of campaign ``folder`` as a YOLO or COCO set in ``out``; ``add_to_export`` writes more
    into the export before it is put in place (the OpenSCENARIO files of the failures) and returns what to add to
    ``export.json``; ``keep(policy, scene, step)`` picks the frames (``harden``: in-ODD failures, before the
    impact); ``extra_frames``: a folder with more frames of the campaign's episodes in its ``frames/`` layout
    (``harden``: near misses rendered again), labelled from the same step data."""
    if fmt not in FORMATS:
        raise UserInputError(f"--format '{fmt}' is unknown; allowed: {', '.join(FORMATS)}")
    output_folder.check_folder_inputs(out, [folder])  # before reading: export CAMP --out CAMP --force wiped CAMP
    meta, rows = load_campaign(folder)
    unknown = sorted(set(policies or []) - set(rows))
    if unknown:
        raise UserInputError(f"--policies: {unknown} not in this campaign; allowed: {', '.join(rows)}")
    modes = {(p, e["scene"]): e["failure_mode"] for p, eps in rows.items() for e in eps}
    # only finished episodes (a summary row exists): an interrupted one may have left frames behind
    found = _frames(folder) + (_frames(extra_frames) if extra_frames is not None else [])
    frames = [f for f in found if (policies is None or f[0] in policies) and (f[0], f[1]) in modes
              and (keep is None or keep(f[0], f[1], f[2]))]
    if not frames:
        hits = sum(1 for p, eps in rows.items() if policies is None or p in policies
                   for e in eps if e.get("first_collision_step") is not None)
        if hits:
            raise UserInputError(f"campaign '{folder}' has {hits} episode(s) with a collision but no kept frames in "
                                 f"'{folder / 'frames'}' (deleted?); re-run those episodes to export them")
        raise UserInputError(f"campaign '{folder}' kept no failure frames (no collisions"
                             f"{' for ' + ','.join(policies) if policies else ''}); nothing to export")
    with output_folder.claim(out, "export", force, inputs=[folder]):
        tmp = out.with_name(f".{out.name}.partial")
        try:
            return _write(folder, fmt, out, tmp, meta, frames, modes, add_to_export)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)  # a failed export leaves no partial folder behind


def _write(folder: Path, fmt: str, out: Path, tmp: Path, meta: dict[str, Any],
           frames: list[tuple[str, int, int, Path]], modes: dict[tuple[str, int], Any],
           add_to_export: Callable[[Path], dict[str, Any]] | None = None) -> dict[str, Any]:
    """Build the export in ``tmp`` beside ``out``, then put it in place of ``out``."""
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    output_folder.write_marker(tmp, "export")
    if fmt == "yolo":
        (tmp / "labels").mkdir()
    steps_cache: dict[tuple[str, int], dict[int, dict[str, Any]]] = {}
    images: list[dict[str, Any]] = []
    annotations: list[dict[str, Any]] = []
    metadata: list[dict[str, Any]] = []
    n_labels = n_ignored = 0
    for image_id, (policy, scene, step, path) in enumerate(frames, start=1):
        key = (policy, scene)
        if key not in steps_cache:
            # a campaign written before a knob existed lacks its column: it reads as the knob's default
            stated = read_episode_row(episode_path(folder, policy, scene))["steps"]  # the file must hold them all
            rows_ = read_steps(steps_path(folder, policy, scene), columns=["step", "gt_boxes", *KNOBS], steps=stated)
            steps_cache[key] = {r["step"]: r for r in rows_}
        rec = steps_cache[key].get(step)
        if rec is None:
            raise UserInputError(f"'{steps_path(folder, policy, scene)}' has no step {step} for the kept frame "
                                 f"'{path}'; {REMEDY}")
        name = f"{policy}_scene{scene:04d}_step{step:04d}"
        try:
            with Image.open(path) as im:
                w, h = im.size
        except (OSError, SyntaxError) as err:  # PIL's UnidentifiedImageError is an OSError
            raise UserInputError(f"frame '{path}' is damaged ({err}); {REMEDY}") from None
        shutil.copyfile(path, tmp / "images" / f"{name}.jpg")
        labels: list[dict[str, Any]] = []
        ignore: list[dict[str, Any]] = []
        for b in (RecordedBox.from_row(row) for row in rec["gt_boxes"]):
            x0, y0, x1, y1 = (float(v) for v in b.box_xyxy)
            x0, x1 = max(0.0, x0), min(float(w), x1)
            y0, y1 = max(0.0, y0), min(float(h), y1)
            if x1 - x0 < 1 or y1 - y0 < 1:
                continue
            box = {"vehicle_id": b.vehicle_id, "xyxy": [x0, y0, x1, y1], "distance_m": b.distance_m,
                   "visible_fraction": b.visible_fraction}
            (labels if b.visible_fraction >= MIN_VISIBLE and y1 - y0 >= MIN_HEIGHT else ignore).append(box)
        n_labels += len(labels)
        n_ignored += len(ignore)
        weather = {k: round(float(v), 3) for k, v in Weather.from_recorded({k: rec[k] for k in KNOBS if k in rec})
                   .values.items()}
        metadata.append({"image": f"images/{name}.jpg", "policy": policy, "scene": scene, "step": step,
                         "failure_mode": modes.get(key), "weather": weather, "labels": labels, "ignore": ignore})
        if fmt == "yolo":
            lines = [f"0 {(b['xyxy'][0] + b['xyxy'][2]) / 2 / w:.6f} {(b['xyxy'][1] + b['xyxy'][3]) / 2 / h:.6f} "
                     f"{(b['xyxy'][2] - b['xyxy'][0]) / w:.6f} {(b['xyxy'][3] - b['xyxy'][1]) / h:.6f}" for b in labels]
            (tmp / "labels" / f"{name}.txt").write_text("\n".join(lines) + ("\n" if lines else ""))
        else:
            images.append({"id": image_id, "file_name": f"images/{name}.jpg", "width": w, "height": h,
                           "genesis_rl": {k: v for k, v in metadata[-1].items() if k not in ("labels", "ignore")}})
            for labelled, crowd in [(b, 0) for b in labels] + [(b, 1) for b in ignore]:
                x0, y0, x1, y1 = labelled["xyxy"]
                annotations.append({"id": len(annotations) + 1, "image_id": image_id, "category_id": 1,
                                    "bbox": [round(x0, 2), round(y0, 2), round(x1 - x0, 2), round(y1 - y0, 2)],
                                    "area": round((x1 - x0) * (y1 - y0), 2), "iscrowd": crowd})
    if fmt == "yolo":
        atomic_write_text(tmp / "data.yaml", "# GENESIS-RL failure frames (genesis-rl export)\n"
                          f"path: .\ntrain: images\nval: images\nnames:\n  0: {CLASSES[0]}\n")
    else:
        atomic_write_json(tmp / "annotations.json", {
            "info": {"description": f"GENESIS-RL failure frames from {folder}",
                     "campaign": meta["spec"], "version": meta.get("package_version")},
            "categories": [{"id": 1, "name": CLASSES[0], "supercategory": "vehicle"}],
            "images": images, "annotations": annotations}, indent=None)
    added = add_to_export(tmp) if add_to_export is not None else {}
    for m in metadata:  # an image's scenario, when the export holds one (records are named POLICY_scene_NNNN)
        xosc = Path("scenarios") / f"{m['policy']}_scene_{m['scene']:04d}.xosc"
        if (tmp / xosc).is_file():
            m["scenario"] = xosc.as_posix()
    atomic_write_text(tmp / "metadata.jsonl", "".join(json.dumps(m) + "\n" for m in metadata))
    result = {"out": str(out), "format": fmt, "images": len(frames), "labels": n_labels, "ignored_boxes": n_ignored,
              "episodes": len({(f[0], f[1]) for f in frames}), **added}
    atomic_write_json(tmp / "export.json", result, indent=2)
    if out.exists():  # replaced only now that the new export is complete
        remove_tree(out)
    tmp.rename(out)
    return result
