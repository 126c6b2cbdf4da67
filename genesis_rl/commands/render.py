"""``genesis-rl render``: one frame of a scene under a weather (rgb, depth, boxes), or a contact sheet of a
sweep of each knob so a person sees each knob's effect at a glance."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from genesis_rl.commands.cli_args import SEED, count
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_text, ensure_writable
from genesis_rl.sim.backends import (
    catalog_or_generate,
)
from genesis_rl.sim.interface import CameraConfig, SensorFrame
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.scenes.catalog import Scene

if TYPE_CHECKING:
    from genesis_rl.sim.lite.backend import LiteBackend

SHOWCASE = ("clear_noon", "dense_fog", "heavy_rain_night", "wet_sunset_glare")


def _save_png(path: Path, img: np.ndarray) -> None:
    from PIL import Image  # local, as cv2 below: `genesis-rl --help` builds every command's parser

    atomic_write(path, lambda p: Image.fromarray(img).save(p, format="PNG"))


def draw_boxes(frame: SensorFrame) -> np.ndarray:
    import cv2

    img = np.ascontiguousarray(frame.rgb.copy())
    for b in frame.boxes:
        cv2.rectangle(img, (b.x0, b.y0), (b.x1 - 1, b.y1 - 1), (40, 255, 40), 1)
        cv2.putText(img, f"{b.vehicle_id}:{b.distance:.0f}m", (b.x0, max(8, b.y0 - 2)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.3, (40, 255, 40), 1, cv2.LINE_AA)
    return img


def depth_to_png(depth: np.ndarray, max_m: float = 100.0) -> np.ndarray:
    """Log-scaled depth as a colour map (near = bright)."""
    import cv2

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
    from genesis_rl.sim.lite.backend import LiteBackend  # local: `genesis-rl --help` builds this parser

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
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    sheet = out / f"contact_sheet_{scene.map}.png"
    ensure_writable(sheet, force)
    rows = sweep_rows()
    from genesis_rl.sim.lite.backend import LiteBackend  # local: `genesis-rl --help` builds this parser

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



def _weather_help() -> str:
    from genesis_rl.world.knobs import KNOBS, PRESETS

    return (f"preset and/or KNOB=VALUE list, e.g. fog_density=60,sun_altitude_angle=10 or heavy_rain_night,"
            f"fog_density=30 (default: clear_noon). Presets: {', '.join(PRESETS)}. Knobs [range]: "
            + ", ".join(f"{k} [{v.low:g}..{v.high:g}]" for k, v in KNOBS.items()))


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``render`` command's flags."""
    p = sub.add_parser("render", help="render a scene's camera frame (rgb, depth, boxes) or a knob sweep sheet")
    p.add_argument("--map", default="urban", help="map name: urban or highway (default: urban; scene generated "
                   "with --seed)")
    p.add_argument("--catalog", default=None, help="take the scene from this catalog file instead")
    p.add_argument("--scene", type=int, action=count(0), default=0, help="scene index (default: 0)")
    p.add_argument("--seed", type=int, action=SEED, default=0, help="catalog seed when no --catalog is given")
    p.add_argument("--weather", default=None, help=_weather_help())
    p.add_argument("--sweep", action="store_true", help="write a contact sheet sweeping each knob")
    p.add_argument("--width", type=int, default=320, help="image width [px] (default: 320)")
    p.add_argument("--height", type=int, default=240, help="image height [px] (default: 240)")
    p.add_argument("--warmup", type=int, action=count(0, limits.SIM_STEPS), default=0,
                   help="simulation steps before the frame")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.commands.render import render_one, render_sweep
    from genesis_rl.sim.interface import CameraConfig
    from genesis_rl.world.knobs import parse_weather

    if args.sweep and args.weather is not None:
        raise UserInputError("--weather does not apply with --sweep: the sheet sweeps each knob from clear noon")
    catalog = catalog_or_generate(args.catalog, args.map, args.scene + 1, args.seed)
    if catalog.backend != "lite":
        raise UserInputError(f"--catalog '{args.catalog}' holds {catalog.backend} scenes; render draws lite scenes "
                             "(allowed: a catalog with backend 'lite')")
    if args.scene >= len(catalog.scenes):
        raise UserInputError(f"--scene {args.scene} is out of range; "
                             f"the catalog has scenes 0..{len(catalog.scenes) - 1}")
    scene = catalog.scene(args.scene)
    try:
        camera = CameraConfig(width=args.width, height=args.height)
    except ValueError as err:
        raise UserInputError(str(err)) from None
    out = Path(args.out)
    if args.sweep:
        result = render_sweep(scene, camera, out, args.force, args.warmup, inputs=[args.catalog])
    else:
        weather = parse_weather(args.weather or "clear_noon")
        result = render_one(scene, weather, camera, out, args.force, args.warmup, inputs=[args.catalog])
    print(json.dumps(result))
    return 0
