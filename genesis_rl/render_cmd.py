"""``genesis-rl render``: one frame of a scene under a weather (rgb, depth, boxes), or a contact sheet of a
sweep of each knob so a person sees each knob's effect at a glance."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from genesis_rl import output_folder
from genesis_rl.io_utils import atomic_write, atomic_write_text, ensure_writable
from genesis_rl.knobs import KNOBS, Weather
from genesis_rl.lite.backend import LiteBackend
from genesis_rl.scenes.catalog import Scene
from genesis_rl.sim.interface import CameraConfig, SensorFrame

SHOWCASE = ("clear_noon", "dense_fog", "heavy_rain_night", "wet_sunset_glare")


def _save_png(path: Path, img: np.ndarray) -> None:
    atomic_write(path, lambda p: Image.fromarray(img).save(p, format="PNG"))


def draw_boxes(frame: SensorFrame) -> np.ndarray:
    img = np.ascontiguousarray(frame.rgb.copy())
    for b in frame.boxes:
        cv2.rectangle(img, (b.x0, b.y0), (b.x1 - 1, b.y1 - 1), (40, 255, 40), 1)
        cv2.putText(img, f"{b.vehicle_id}:{b.distance:.0f}m", (b.x0, max(8, b.y0 - 2)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.3, (40, 255, 40), 1, cv2.LINE_AA)
    return img


def depth_to_png(depth: np.ndarray, max_m: float = 100.0) -> np.ndarray:
    """Log-scaled depth as a colour map (near = bright)."""
    d = np.clip(np.log1p(depth) / np.log1p(max_m), 0, 1)
    return cv2.applyColorMap(((1 - d) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]


def _frame(backend: LiteBackend, scene: Scene, weather: Weather, camera: CameraConfig, warmup: int) -> SensorFrame:
    with backend.create_simulation(scene, seed=0, weather=weather, camera=camera) as sim:
        for _ in range(warmup):
            sim.tick()
        return sim.observe()


RENDER_OUTPUTS = ("rgb.png", "depth.png", "boxes.png", "boxes.json")


def render_one(scene: Scene, weather: Weather, camera: CameraConfig, out: Path, force: bool, warmup: int = 0,
               inputs: Sequence[str | Path | None] = ()) -> dict:
    """rgb.png, depth.png, boxes.png and boxes.json of one frame, written into ``out`` while holding it."""
    with output_folder.claim(out, "render", force, files=RENDER_OUTPUTS, inputs=inputs) as fresh:
        result = _render_one(scene, weather, camera, out, force, warmup)
        if fresh:
            output_folder.write_marker(out, "render")
    return result


def _render_one(scene: Scene, weather: Weather, camera: CameraConfig, out: Path, force: bool, warmup: int) -> dict:
    for name in RENDER_OUTPUTS:
        ensure_writable(out / name, force)
    backend = LiteBackend()
    try:
        frame = _frame(backend, scene, weather, camera, warmup)
    finally:
        backend.close()
    _save_png(out / "rgb.png", frame.rgb)
    _save_png(out / "depth.png", depth_to_png(frame.depth))
    _save_png(out / "boxes.png", draw_boxes(frame))
    info = {"map": scene.map, "scene": scene.index, "weather": weather.as_dict(),
            "width": camera.width, "height": camera.height, "boxes": [b.as_dict() for b in frame.boxes]}
    atomic_write_text(out / "boxes.json", json.dumps(info, indent=2))
    return {"out": str(out), "boxes": len(frame.boxes)}


def sweep_rows() -> list[tuple[str, list[tuple[str, Weather]]]]:
    """The contact sheet's rows: one per knob that declares sweep values (``KnobSpec.sweep``), each on top of
    clear noon, then the showcase presets."""
    rows = [(k.name, [(f"{k.name}={v:g}", Weather.default().replace(**k.sweep_base, **{k.name: v}))
                      for v in k.sweep]) for k in KNOBS.values() if k.sweep]
    rows.append(("showcase", [(n, Weather.preset(n)) for n in SHOWCASE]))
    return rows


def render_sweep(scene: Scene, camera: CameraConfig, out: Path, force: bool, warmup: int = 0,
                 inputs: Sequence[str | Path | None] = ()) -> dict:
    """A contact sheet: one row per knob sweep plus a row of showcase weathers, written while holding ``out``."""
    name = f"contact_sheet_{scene.map}.png"
    with output_folder.claim(out, "render", force, files=[name], inputs=inputs) as fresh:
        result = _render_sweep(scene, camera, out, force, warmup)
        if fresh:
            output_folder.write_marker(out, "render")
    return result


def _render_sweep(scene: Scene, camera: CameraConfig, out: Path, force: bool, warmup: int) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sheet = out / f"contact_sheet_{scene.map}.png"
    ensure_writable(sheet, force)
    rows = sweep_rows()
    backend = LiteBackend()
    cols = max(len(r[1]) for r in rows)
    fig, axes = plt.subplots(len(rows), cols, figsize=(cols * 2.6, len(rows) * 2.05))
    try:
        for r, (_, items) in enumerate(rows):
            for c in range(cols):
                ax = axes[r, c]
                ax.axis("off")
                if c < len(items):
                    title, weather = items[c]
                    ax.imshow(_frame(backend, scene, weather, camera, warmup).rgb)
                    ax.set_title(title, fontsize=7)
    finally:
        backend.close()
    fig.suptitle(f"GENESIS-RL lite: map '{scene.map}', scene {scene.index}: one knob at a time from clear noon "
                 "(azimuth row: sun at 12 deg)",
                 fontsize=10)
    fig.tight_layout()
    atomic_write(sheet, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)
    return {"out": str(sheet)}
