"""``genesis-rl drive``: the system under test drives scenes closed-loop; telemetry, GIF and summary."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from genesis_rl.commands.cli_args import SEED, count
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write_json, ensure_writable
from genesis_rl.sim.backends import (
    add_backend_arguments,
    backend_from_args,
    catalog_or_generate,
    check_backend_setting,
)
from genesis_rl.world.knobs import Weather
from genesis_rl.world.scenes.catalog import Catalog, Scene

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

    from genesis_rl.loop.drive import run_episode, write_telemetry
    from genesis_rl.loop.frames import annotate_frame, write_gif
    from genesis_rl.sim.interface import CameraConfig
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sut.system.protocol import load_system

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



def _weather_help() -> str:
    from genesis_rl.world.knobs import KNOBS, PRESETS

    return (f"preset and/or KNOB=VALUE list, e.g. fog_density=60,sun_altitude_angle=10 or heavy_rain_night,"
            f"fog_density=30 (default: clear_noon). Presets: {', '.join(PRESETS)}. Knobs [range]: "
            + ", ".join(f"{k} [{v.low:g}..{v.high:g}]" for k, v in KNOBS.items()))


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``drive`` command's flags."""
    p = sub.add_parser("drive", help="drive the system under test closed-loop; telemetry, GIF, summary")
    p.add_argument("--map", default="highway",
                   help="map name: urban or highway (default: highway; scenes generated with --seed)")
    p.add_argument("--catalog", default=None, help="take scenes from this catalog file instead")
    p.add_argument("--scene", default="0", help="scene index (3) or range START:STOP (0:50); default: 0")
    p.add_argument("--seed", type=int, action=SEED, default=0, help="catalog seed when no --catalog is given")
    p.add_argument("--episode-seed", type=int, action=SEED, default=0, help="seed of NPC behaviour and sensor noise")
    p.add_argument("--weather", default="clear_noon", help=_weather_help() + ". The base of --schedule.")
    p.add_argument("--schedule", default=None, help="CSV of per-step knob values: one row a step, one column a knob")
    p.add_argument("--system", default="builtin",
                   help="system under test: builtin, blind, oracle, yolo, coco, latency, or package.module:Class "
                        "(default: builtin)")
    p.add_argument("--weights", default=None,
                   help="detector weights for --system builtin or yolo (default: the shipped ones), or the "
                        "model folder for coco (default: the model store)")
    p.add_argument("--steps", type=int, action=count(1, limits.SIM_STEPS), default=512,
                   help="steps per episode, 0.05 s each (default: 512)")
    p.add_argument("--width", type=int, default=320, help="camera width [px] (default: 320)")
    p.add_argument("--height", type=int, default=240, help="camera height [px] (default: 240)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--no-gif", action="store_true", help="skip the animation")
    p.add_argument("--gif", action="store_true", help="also write a GIF per scene when driving a range")
    p.add_argument("--gif-stride", type=int, default=2, help="keep every Nth frame in the GIF (default: 2)")
    p.add_argument("--gif-from", type=int, default=0, help="first step shown in the GIF (default: 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--threads", type=int, action=count(1, limits.THREADS), default=1,
                   help="torch CPU threads for the system under test (default 1: the arithmetic of evaluate and "
                        "replay, and no slowdown when several processes share the cores)")
    add_backend_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.commands.drive import drive_scenes, parse_scene_range, print_summary
    from genesis_rl.world.knobs import parse_weather
    from genesis_rl.world.weather_schedule import load_schedule

    if not 1 <= args.gif_stride <= args.steps:  # a stride past the episode keeps one frame; past 2**63 overflows
        raise UserInputError(f"--gif-stride = {args.gif_stride}; allowed: 1..{args.steps} (--steps)")
    if args.gif_from < 0 or args.gif_from >= args.steps:
        raise UserInputError(f"--gif-from must be a step in 0..{args.steps - 1} (--steps {args.steps}), "
                             f"got {args.gif_from}")
    if args.gif and args.no_gif:
        raise UserInputError("--gif and --no-gif contradict each other; pass one")
    indices = parse_scene_range(args.scene)
    kind = check_backend_setting(args.backend, args.catalog, "--backend", "--catalog").catalog_kind
    catalog = catalog_or_generate(args.catalog, args.map, max(indices) + 1, args.seed, backend=args.backend)
    if catalog.backend != kind:
        raise UserInputError(f"--catalog '{args.catalog}' holds {catalog.backend} scenes; pass --backend "
                             f"{catalog.backend} or a catalog made for --backend {args.backend}")
    parse_scene_range(args.scene, len(catalog.scenes))
    base = parse_weather(args.weather)
    schedule = load_schedule(args.schedule, base, args.steps) if args.schedule else None
    kwargs = {}
    if args.weights:
        from genesis_rl.sut.system.protocol import WEIGHTED_SYSTEMS

        if args.system not in WEIGHTED_SYSTEMS:
            raise UserInputError(f"--weights applies to --system {', '.join(WEIGHTED_SYSTEMS)} only")
        kwargs["weights"] = args.weights
    import torch

    threads_before = torch.get_num_threads()
    torch.set_num_threads(args.threads)  # for this run only: main() is also called from tests and notebooks
    try:
        summary = drive_scenes(catalog, indices, args.system, kwargs, base, schedule, args.steps, args.episode_seed,
                               Path(args.out), args.force, gif=not args.no_gif and (len(indices) == 1 or args.gif),
                               gif_stride=args.gif_stride, gif_from=args.gif_from,
                               camera_size=(args.width, args.height),
                               progress=not args.quiet, backend_factory=lambda: backend_from_args(args),
                               inputs=[args.catalog, args.schedule, args.weights])
    finally:
        torch.set_num_threads(threads_before)
    print_summary(summary)
    return 0
