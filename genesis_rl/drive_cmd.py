"""``genesis-rl drive``: the system under test drives scenes closed-loop; telemetry, GIF and summary."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from genesis_rl import limits, output_folder
from genesis_rl.errors import UserInputError
from genesis_rl.io_utils import atomic_write_json, ensure_writable
from genesis_rl.knobs import Weather
from genesis_rl.scenes.catalog import Catalog, Scene

if TYPE_CHECKING:
    import numpy as np

    from genesis_rl.sim.interface import Backend


def parse_scene_range(text: str, catalog_size: int | None = None) -> list[int]:
    """``3`` -> [3]; ``0:50`` -> [0..49]. Errors name the flag and the allowed form."""
    try:
        start, stop = (int(v) for v in text.split(":", 1)) if ":" in text else (int(text), int(text) + 1)
    except ValueError:
        raise UserInputError(f"--scene '{text}' must be an index (3) or a range START:STOP (0:50)") from None
    limits.SCENES.check(stop, "--scene", text)  # before the list is built: 0:10**12 would exhaust memory
    idx = list(range(start, stop))
    if not idx or min(idx) < 0:
        raise UserInputError(f"--scene '{text}' selects no scene; indices start at 0")
    if catalog_size is not None and max(idx) >= catalog_size:
        raise UserInputError(f"--scene '{text}' is out of range; the catalog has {catalog_size} scenes")
    return idx


def drive_scenes(
    catalog: Catalog,
    scene_indices: list[int],
    system_spec: str,
    system_kwargs: dict[str, Any],
    base_weather: Weather,
    schedule: list[Weather] | None,
    steps: int,
    seed: int,
    out: Path,
    force: bool,
    gif: bool,
    gif_stride: int = 2,
    gif_from: int = 0,
    camera_size: tuple[int, int] = (320, 240),
    progress: bool = True,
    backend_factory: Callable[[], Backend] | None = None,
    inputs: Sequence[str | Path | None] = (),
) -> dict[str, Any]:
    """Drive each scene, holding ``out``; ``backend_factory`` makes the simulator (default: lite); ``inputs``
    are the files the command reads (catalog, schedule, weights), which no output may replace."""
    single = len(scene_indices) == 1
    names = ["summary.json", *(_output_name("telemetry", "parquet", i, single) for i in scene_indices),
             *((_output_name("drive", "gif", i, single) for i in scene_indices) if gif else [])]
    with output_folder.claim(out, "drive", force, files=names, inputs=inputs) as fresh:
        summary = _drive_scenes(catalog, scene_indices, system_spec, system_kwargs, base_weather, schedule, steps,
                                seed, out, force, gif, gif_stride, gif_from, camera_size, progress, backend_factory)
        if fresh:
            output_folder.write_marker(out, "drive")
    return summary


def _output_name(stem: str, suffix: str, scene: int, single: bool) -> str:
    return f"{stem}.{suffix}" if single else f"{stem}_scene_{scene:04d}.{suffix}"


def _drive_scenes(catalog: Catalog, scene_indices: list[int], system_spec: str, system_kwargs: dict[str, Any],
                  base_weather: Weather, schedule: list[Weather] | None, steps: int, seed: int, out: Path,
                  force: bool, gif: bool, gif_stride: int, gif_from: int, camera_size: tuple[int, int],
                  progress: bool, backend_factory: Callable[[], Backend] | None) -> dict[str, Any]:
    from tqdm import tqdm

    from genesis_rl.drive import run_episode, write_telemetry
    from genesis_rl.lite.backend import LiteBackend
    from genesis_rl.sim.interface import CameraConfig
    from genesis_rl.system.protocol import load_system
    from genesis_rl.viz.frames import annotate_frame, write_gif

    single = len(scene_indices) == 1

    def telemetry_path(i: int) -> Path:
        return out / _output_name("telemetry", "parquet", i, single)

    def gif_path(i: int) -> Path:
        return out / _output_name("drive", "gif", i, single)

    summary_path = out / "summary.json"
    # refuse before driving: no earlier result is overwritten without --force, whichever file it is
    for path in [summary_path, *map(telemetry_path, scene_indices), *(map(gif_path, scene_indices) if gif else [])]:
        ensure_writable(path, force)
    system = load_system(system_spec, **system_kwargs)
    try:
        camera = CameraConfig(width=camera_size[0], height=camera_size[1])
    except ValueError as err:
        raise UserInputError(str(err)) from None

    def weather_at(step: int) -> Weather:
        return schedule[step] if schedule is not None else base_weather

    rows = []
    with (backend_factory() if backend_factory else LiteBackend()) as backend:
        bar = tqdm(scene_indices, desc="scenes", unit="scene", disable=not progress or single)
        for i in bar:
            scene: Scene = catalog.scene(i)
            frames: list[np.ndarray] = []

            def hook(step: int, frame, out_, rec, frames=frames) -> None:  # noqa: ANN001
                if gif and step >= gif_from and (step - gif_from) % gif_stride == 0:
                    frames.append(annotate_frame(frame.rgb, rec))

            result = run_episode(backend, scene, system, weather_at, steps, seed, camera, hook,
                                 progress=progress and single)
            write_telemetry(telemetry_path(i), result.records)
            if gif and frames:
                write_gif(gif_path(i), frames,
                          fps=1.0 / (0.05 * gif_stride))
            row = {"scene": i, **result.summary()}
            rows.append(row)
            if not single:
                bar.set_postfix(collisions=sum(r["collisions"] > 0 for r in rows))
    collided = sum(r["collisions"] > 0 for r in rows)
    summary = {
        "map": catalog.map,
        "scenes": scene_indices if len(scene_indices) <= 10 else f"{scene_indices[0]}:{scene_indices[-1] + 1}",
        "steps": steps,
        "seed": seed,
        "system": system.identity(),
        "weather": base_weather.as_dict() if schedule is None else "schedule",
        "episodes": len(rows),
        "episodes_with_collision": collided,
        "collision_free_rate": round(1.0 - collided / len(rows), 4),
        "per_scene": rows,
    }
    atomic_write_json(summary_path, summary, indent=2)
    return summary


def print_summary(summary: dict[str, Any]) -> None:
    rows = summary["per_scene"]
    if len(rows) == 1:
        print(json.dumps({k: v for k, v in summary.items() if k != "per_scene"} | rows[0], indent=2))
        return
    print(f"{'scene':>5} {'coll':>4} {'speed@hit':>9} {'prox':>5} {'min gap':>8} {'IoU':>5} {'dist m':>7}")
    for r in rows:
        mg = "-" if r["min_true_gap"] is None else f"{r['min_true_gap']:.1f}"
        print(f"{r['scene']:>5} {r['collisions']:>4} {r['collision_speed']:>9.1f} {r['proximity_steps']:>5} "
              f"{mg:>8} {r['mean_iou']:>5.2f} {r['distance_m']:>7.0f}")
    print(f"collision-free: {len(rows) - summary['episodes_with_collision']}/{len(rows)} "
          f"({100 * summary['collision_free_rate']:.0f}%)")
