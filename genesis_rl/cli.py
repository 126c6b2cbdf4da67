"""The ``genesis-rl`` command line. Bad input exits with status 2 and a one-line message, no traceback.

Each subcommand imports what it runs inside its handler (local imports on purpose): ``genesis-rl --help`` and
a mistyped flag answer in 0.45 s instead of 3.2 s (what importing torch, Panda3D and the campaign code costs)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any

from genesis_rl import __version__, limits
from genesis_rl.backends import (
    add_backend_arguments,
    backend_class,
    backend_from_args,
    catalog_or_generate,
    check_backend_setting,
    env_overrides_from_args,
    scene_source,
    settings_from_args,
)
from genesis_rl.cli_args import add_odd_arguments, add_scale_arguments, odd_overrides_from_args, seed_int
from genesis_rl.errors import UserInputError
from genesis_rl.io_utils import os_error_message
from genesis_rl.plugins import import_env_plugins
from genesis_rl.signals import exit_status, interrupts_raise, resume_hint
from genesis_rl.trust import add_trust_arguments, trusted_for


def _weather_help() -> str:
    from genesis_rl.knobs import KNOBS, PRESETS

    return (f"preset and/or KNOB=VALUE list, e.g. fog_density=60,sun_altitude_angle=10 or heavy_rain_night,"
            f"fog_density=30 (default: clear_noon). Presets: {', '.join(PRESETS)}. Knobs [range]: "
            + ", ".join(f"{k} [{v.low:g}..{v.high:g}]" for k, v in KNOBS.items()))


def _cmd_scenes(args: argparse.Namespace) -> int:
    from genesis_rl.output_paths import output_file

    source = scene_source(backend_class(args.backend).catalog_kind)
    source.check_map(args.map, "--map")
    count = args.count if args.count is not None else source.default_count(args.map)
    if count < 1:
        raise UserInputError(f"--count must be >= 1, got {count}")
    limits.SCENES.check(count, "--count")
    if count < 1:
        raise UserInputError(f"--count must be >= 1, got {count}")
    limits.SCENES.check(count, "--count")
    out = output_file(args.out, args.force)
    t0 = time.perf_counter()
    if args.generator == "scenic":
        from genesis_rl.scenic_scenes import generator as scenic_generator

        if backend_class(args.backend).catalog_kind == "carla":
            catalog = scenic_generator.carla_catalog_from_server(args.map, count, args.seed, settings_from_args(args),
                                                                 progress=not args.quiet)
        else:
            catalog = scenic_generator.lite_catalog(args.map, count, args.seed, progress=not args.quiet)
    else:
        catalog = source.generate(args.map, count, args.seed, settings_from_args(args), progress=not args.quiet)
    out.write_json(catalog.to_json())
    backend = {} if catalog.backend == "lite" else {"backend": catalog.backend}  # lite's line as it always was
    print(json.dumps({"out": str(out), "map": args.map, **backend, "scenes": count, "seed": args.seed,
                      "seconds": round(time.perf_counter() - t0, 2)}), file=out.status)
    return 0


def _cmd_map(args: argparse.Namespace) -> int:
    from genesis_rl.lite.maps import load_map
    from genesis_rl.lite.maps.opendrive import to_opendrive
    from genesis_rl.lite.scenes import check_map
    from genesis_rl.output_paths import output_file

    check_map(args.map, "--map")
    out = output_file(args.out if args.out else f"{args.map}.xodr", args.force)
    t0 = time.perf_counter()
    road_map = load_map(args.map)
    text = to_opendrive(road_map)
    out.write_text(text)
    print(json.dumps({"out": str(out), "map": args.map, "format": args.format, "roads": len(road_map.roads),
                      "junctions": len(road_map.junctions), "lanes": len(road_map.lanes), "bytes": len(text.encode()),
                      "seconds": round(time.perf_counter() - t0, 2)}), file=out.status)
    return 0


def _cmd_reactivity(args: argparse.Namespace) -> int:
    from genesis_rl.evaluation.reactivity import measure_campaign
    from genesis_rl.output_paths import output_file

    out = output_file(args.out if args.out else Path(args.campaign) / f"reactivity_{args.policy}.json", args.force,
                      inputs=[args.campaign], products=[r"reactivity_[\w.-]*\.json"])
    t0 = time.perf_counter()
    result = measure_campaign(args.campaign, args.policy, args.scenes, not args.no_other_seeds,
                              progress=not args.quiet)
    data = {"campaign": str(args.campaign), "policy": args.policy, **result.to_json(),
            "seconds": round(time.perf_counter() - t0, 1)}
    out.write_json(data, indent=2)
    short = {kind: {m: {"gap": g["difference"]["mean"], "ci": [g["difference"]["ci_low"], g["difference"]["ci_high"]],
                        "p": g["p_value"]} for m, g in gaps.items()} for kind, gaps in data["gaps"].items()}
    print(json.dumps({"out": str(out), "policy": args.policy, "scenes": len(result.rows) // max(len(data["gaps"]), 1),
                      "gaps": short, "seconds": data["seconds"]}, indent=2), file=out.status)
    return 0


def _cmd_corners(args: argparse.Namespace) -> int:
    if args.steps is not None:  # before anything is imported or built: --steps 1000000000000 would run for years
        if args.steps < 1:
            raise UserInputError(f"--steps must be >= 1, got {args.steps}")
        limits.SIM_STEPS.check(args.steps, "--steps")
    if args.scenes < 1:
        raise UserInputError(f"--scenes must be >= 1, got {args.scenes}")
    limits.SCENES.check(args.scenes, "--scenes")
    from genesis_rl.env import GenesisEnv
    from genesis_rl.evaluation.campaign_spec import pick_scenes
    from genesis_rl.evaluation.corners import search_corners
    from genesis_rl.output_paths import check_inputs, output_file
    from genesis_rl.training.config import load_run_config

    out = output_file(args.out, args.force, inputs=[args.config])
    env_over: dict = {"episode_steps": args.steps} if args.steps is not None else {}
    if args.map is not None:
        env_over["map"] = args.map
    cfg = load_run_config(args.config, {"env": env_over})
    check_inputs(args.out, [cfg.env.catalog, cfg.env.odd, cfg.env.rulebook])  # the files the config names
    env = GenesisEnv(cfg.env)
    try:
        pairs = pick_scenes(len(env.catalog.scenes), args.scenes, args.seed)
        t0 = time.perf_counter()
        rows = search_corners(env, [s for s, _ in pairs], [e for _, e in pairs], progress=not args.quiet)
    finally:
        env.close()
    best = ",".join(f"{v:g}" for v in rows[0]["action"])
    out.write_json({"config": args.config, "map": cfg.env.map, "scenes": pairs, "knobs": list(cfg.env.knobs),
                            "steps": cfg.env.episode_steps, "best_constant_action": best, "corners": rows,
                            "seconds": round(time.perf_counter() - t0, 1)}, indent=2)
    print(json.dumps({"out": str(out), "best_constant_action": best, "mean_return": round(rows[0]["mean_return"], 3),
                      "collisions": rows[0]["collisions"], "corners": len(rows),
                      "then": f"genesis-rl evaluate --policies constant --constant-action {best} ..."}, indent=2),
          file=out.status)
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from genesis_rl.knobs import parse_weather
    from genesis_rl.render_cmd import render_one, render_sweep
    from genesis_rl.sim.interface import CameraConfig

    if args.scene < 0:
        raise UserInputError(f"--scene must be >= 0, got {args.scene}")
    if args.warmup < 0:
        raise UserInputError(f"--warmup must be >= 0, got {args.warmup}")
    limits.SIM_STEPS.check(args.warmup, "--warmup")
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


def _cmd_drive(args: argparse.Namespace) -> int:
    from genesis_rl.drive_cmd import drive_scenes, parse_scene_range, print_summary
    from genesis_rl.knobs import parse_weather
    from genesis_rl.weather_schedule import load_schedule

    if args.steps < 1:
        raise UserInputError(f"--steps must be >= 1, got {args.steps}")
    limits.SIM_STEPS.check(args.steps, "--steps")
    if not 1 <= args.gif_stride <= args.steps:  # a stride past the episode keeps one frame; past 2**63 overflows
        raise UserInputError(f"--gif-stride = {args.gif_stride}; allowed: 1..{args.steps} (--steps)")
    if args.threads < 1:
        raise UserInputError(f"--threads must be >= 1, got {args.threads}")
    limits.THREADS.check(args.threads, "--threads")
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
        from genesis_rl.system.protocol import WEIGHTED_SYSTEMS

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


def _csv_list(text: str | None) -> list[str] | None:
    return None if text is None else [t.strip() for t in text.split(",") if t.strip()]


def _cmd_train(args: argparse.Namespace) -> int:
    from genesis_rl.knobs import KNOBS
    from genesis_rl.training.config import load_run_config
    from genesis_rl.training.train import train

    env: dict = {}
    for flag, key in (("knobs", "knobs"), ("disable_knobs", "disabled_knobs")):
        names = _csv_list(getattr(args, flag))
        if names is not None:
            bad = [n for n in names if n not in KNOBS]
            if bad:
                raise UserInputError(f"--{flag.replace('_', '-')}: unknown knob(s) {bad}; allowed: {', '.join(KNOBS)}")
            env[key] = names
    for flag in ("system", "scenes", "catalog", "map"):
        if getattr(args, flag) is not None:
            env[flag] = getattr(args, flag)
    if args.map is not None and args.catalog is not None:  # the run would record a map its scenes are not on
        from genesis_rl.evaluation.campaign_spec import campaign_map

        campaign_map(args.map, args.catalog)
    env.update(env_overrides_from_args(args))  # --backend carla --carla-host H ... override the config's [env]
    env.update(odd_overrides_from_args(args))
    tr: dict = {}
    for flag, key in (("envs", "envs"), ("steps", "total_timesteps"), ("seed", "seed"), ("algorithm", "algorithm")):
        if getattr(args, flag) is not None:
            tr[key] = getattr(args, flag)
    ppo = {"n_steps": args.n_steps} if args.n_steps is not None else {}
    if args.episode_steps is not None:
        env["episode_steps"] = args.episode_steps
    extra = {k: v for k, v in tr.items() if k != "total_timesteps"}
    if args.resume and (env or extra or ppo or args.config):
        raise UserInputError("--resume continues a run with its own config.toml; only --steps may change")
    cfg = load_run_config(args.config, {"env": env, "train": tr, "ppo": ppo})
    from genesis_rl.backends import servers_text
    from genesis_rl.distributed.servers import parse_servers
    from genesis_rl.distributed.settings import ExecutorSettings

    scale = ExecutorSettings(kind=args.executor, ray_address=args.ray_address,
                             servers=parse_servers(servers_text(args)))
    result = train(cfg, Path(args.out), force=args.force, resume=args.resume, progress=not args.quiet,
                   argv=sys.argv, total_timesteps=args.steps if args.resume else None, inputs=[args.config],
                   scale=scale)
    print(json.dumps(result, indent=2))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    steps = args.steps if args.steps is not None else {"sim": 2000, "system": 200, "train": 2048,
                                                       "campaign": 256}[args.what]
    least = 2 if args.what == "train" else 1  # a PPO update needs two steps
    if steps < least:
        raise UserInputError(f"--steps = {steps} must be >= {least}")
    if args.frames < 1:
        raise UserInputError(f"--frames = {args.frames} must be >= 1")
    limits.SIM_STEPS.check(steps, "--steps")
    limits.FRAMES.check(args.frames, "--frames")  # bench system --frames 1000000000 would run for years
    from genesis_rl.bench import bench_campaign, bench_sim, bench_system, bench_train

    if args.what == "campaign":
        executors = tuple(t.strip() for t in (args.executors or "local,ray").split(","))
        bad = [e for e in executors if e not in ("local", "ray")]  # an empty item (ray,,local) is a typo too
        if bad or not executors or len(set(executors)) < len(executors):
            raise UserInputError(f"--executors {args.executors!r}; allowed: a comma list of local, ray (each once, "
                                 "no empty items)")
        counts = limits.count_list(args.workers, "--workers", limits.WORKERS)  # 1,,2 is refused
        if not 1 <= args.scenes <= 500:
            raise UserInputError(f"--scenes = {args.scenes} must be in 1..500")
        print(json.dumps(bench_campaign(scenes=args.scenes, steps=steps, executors=executors, workers=counts,
                                        system=args.system), indent=2))
        return 0
    if args.what == "train":
        if not 1 <= args.envs <= 64 or not 1 <= args.updates <= 100:
            raise UserInputError(f"--envs = {args.envs} must be in 1..64 and --updates = {args.updates} in 1..100")
        if steps % args.envs:
            raise UserInputError(f"--steps = {steps} must be a multiple of --envs = {args.envs}")
        executor = args.executors or "local"
        if executor not in ("local", "ray"):
            raise UserInputError(f"--executors {executor!r}: bench train takes one of local, ray")
        print(json.dumps(bench_train(args.config, envs=args.envs, updates=args.updates, n_steps=steps,
                                     system=args.system, executor=executor), indent=2))
        return 0
    if args.what == "system":
        print(json.dumps(bench_system(frames=args.frames, steps=steps, system=args.system), indent=2))
        return 0
    print(json.dumps(bench_sim(physics_steps=steps, frames=args.frames, render=not args.no_render), indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="genesis-rl",
        description="GENESIS-RL: find natural edge cases for autonomous driving by turning the weather.",
    )
    p.add_argument("--version", action="version", version=f"genesis-rl {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    sc = sub.add_parser("scenes", help="generate a scene catalog (JSON) for a map")
    sc.add_argument("--map", default="urban", help="map name: urban (train) or highway (test); default: urban")
    sc.add_argument("--count", type=int, default=None, help="number of scenes (default: 1202 urban, 1199 highway)")
    sc.add_argument("--seed", type=seed_int, default=0, help="catalog seed: the same seed gives the same catalog")
    sc.add_argument("--generator", default="builtin", choices=["builtin", "scenic"],
                    help="builtin (default) or scenic: the paper's Scenic 3 program (pip install -e .[scenic]; "
                         "lite maps through their OpenDRIVE export, CARLA maps from the server)")
    add_backend_arguments(sc)
    sc.add_argument("--out", required=True, help="output catalog file (.json)")
    sc.add_argument("--force", action="store_true", help="overwrite an existing output")
    sc.add_argument("--quiet", action="store_true", help="no progress bar")
    sc.set_defaults(func=_cmd_scenes)

    mp = sub.add_parser("map", help="export a lite map as OpenDRIVE (for CARLA and Scenic)",
                        description="Write a lite map as OpenDRIVE 1.4: roads, lanes, junctions and traffic lights. "
                        "CARLA builds a carla.Map from it without a server, a CARLA server drives it with "
                        "client.generate_opendrive_world, and Scenic loads it as a road network (docs/carla.md).")
    mp.add_argument("action", choices=["export"], help="what to do: export")
    mp.add_argument("--map", default="urban", help="lite map: urban or highway (default: urban)")
    mp.add_argument("--format", default="xodr", choices=["xodr"], help="output format (default: xodr, OpenDRIVE 1.4)")
    mp.add_argument("--out", default=None, help="output file (default: MAP.xodr in the current folder)")
    mp.add_argument("--force", action="store_true", help="overwrite an existing output")
    mp.set_defaults(func=_cmd_map)

    rx = sub.add_parser("reactivity", help="closed-loop against open-loop: does a policy react to the scene?",
                        description="Play a campaign's step policy closed-loop on its scenes, then its action "
                        "sequences open-loop on the next scene (and on the same scene with another episode seed); "
                        "report the gaps (closed minus open) in return, collisions and collision violation with "
                        "bootstrap CIs and sign-flip p-values. A fixed schedule has no gap (docs/results.md).")
    rx.add_argument("--campaign", required=True, help="campaign folder (genesis-rl evaluate --out)")
    rx.add_argument("--policy", default="agent", help="step policy of the campaign: agent (default), constant, "
                    "random, sunny or package.module:Class")
    rx.add_argument("--scenes", type=int, default=None, help="the campaign's first N scenes (default: all)")
    rx.add_argument("--no-other-seeds", action="store_true", help="skip the same-scene, other-seed comparison "
                    "(halves the cost: 2 episodes a scene instead of 4)")
    rx.add_argument("--out", default=None, help="output JSON (default: CAMPAIGN/reactivity_POLICY.json)")
    rx.add_argument("--force", action="store_true", help="overwrite an existing output")
    rx.add_argument("--quiet", action="store_true", help="no progress bar")
    rx.set_defaults(func=_cmd_reactivity)

    cn = sub.add_parser("corners", help="find the best constant schedule: every corner of the action box on "
                        "training scenes", description="Play every corner of the action box (+-1 on each knob that "
                        "can move) on the same training scenes and seeds; rank by mean return, then collisions. The "
                        "winner is the open-loop baseline for evaluate --policies constant --constant-action.")
    cn.add_argument("--config", default=None, help="TOML config whose [env] is used (e.g. configs/reactive.toml)")
    cn.add_argument("--map", default=None, help="map of the scenes (default: the config's env.map, the training map)")
    cn.add_argument("--scenes", type=int, default=10, help="training scenes drawn by --seed (default: 10)")
    cn.add_argument("--seed", type=seed_int, default=0, help="draws the scenes and their episode seeds")
    cn.add_argument("--steps", type=int, default=None, help="steps per episode (default: the config's)")
    cn.add_argument("--out", required=True, help="output JSON")
    cn.add_argument("--force", action="store_true", help="overwrite an existing output")
    cn.add_argument("--quiet", action="store_true", help="no progress bar")
    cn.set_defaults(func=_cmd_corners)

    rd = sub.add_parser("render", help="render a scene's camera frame (rgb, depth, boxes) or a knob sweep sheet")
    rd.add_argument("--map", default="urban", help="map name: urban or highway (default: urban; scene generated "
                    "with --seed)")
    rd.add_argument("--catalog", default=None, help="take the scene from this catalog file instead")
    rd.add_argument("--scene", type=int, default=0, help="scene index (default: 0)")
    rd.add_argument("--seed", type=seed_int, default=0, help="catalog seed when no --catalog is given")
    rd.add_argument("--weather", default=None, help=_weather_help())
    rd.add_argument("--sweep", action="store_true", help="write a contact sheet sweeping each knob")
    rd.add_argument("--width", type=int, default=320, help="image width [px] (default: 320)")
    rd.add_argument("--height", type=int, default=240, help="image height [px] (default: 240)")
    rd.add_argument("--warmup", type=int, default=0, help="simulation steps before the frame")
    rd.add_argument("--out", required=True, help="output directory")
    rd.add_argument("--force", action="store_true", help="overwrite existing outputs")
    rd.set_defaults(func=_cmd_render)

    dr = sub.add_parser("drive", help="drive the system under test closed-loop; telemetry, GIF, summary")
    dr.add_argument("--map", default="highway",
                    help="map name: urban or highway (default: highway; scenes generated with --seed)")
    dr.add_argument("--catalog", default=None, help="take scenes from this catalog file instead")
    dr.add_argument("--scene", default="0", help="scene index (3) or range START:STOP (0:50); default: 0")
    dr.add_argument("--seed", type=seed_int, default=0, help="catalog seed when no --catalog is given")
    dr.add_argument("--episode-seed", type=seed_int, default=0, help="seed of NPC behaviour and sensor noise")
    dr.add_argument("--weather", default="clear_noon", help=_weather_help() + ". The base of --schedule.")
    dr.add_argument("--schedule", default=None, help="CSV of per-step knob values: one row a step, one column a knob")
    dr.add_argument("--system", default="builtin",
                    help="system under test: builtin, blind, oracle, yolo, coco, latency, or package.module:Class "
                         "(default: builtin)")
    dr.add_argument("--weights", default=None,
                    help="detector weights for --system builtin or yolo (default: the shipped ones), or the "
                         "model folder for coco (default: the model store)")
    dr.add_argument("--steps", type=int, default=512, help="steps per episode, 0.05 s each (default: 512)")
    dr.add_argument("--width", type=int, default=320, help="camera width [px] (default: 320)")
    dr.add_argument("--height", type=int, default=240, help="camera height [px] (default: 240)")
    dr.add_argument("--out", required=True, help="output directory")
    dr.add_argument("--force", action="store_true", help="overwrite existing outputs")
    dr.add_argument("--no-gif", action="store_true", help="skip the animation")
    dr.add_argument("--gif", action="store_true", help="also write a GIF per scene when driving a range")
    dr.add_argument("--gif-stride", type=int, default=2, help="keep every Nth frame in the GIF (default: 2)")
    dr.add_argument("--gif-from", type=int, default=0, help="first step shown in the GIF (default: 0)")
    dr.add_argument("--quiet", action="store_true", help="no progress bar")
    dr.add_argument("--threads", type=int, default=1,
                    help="torch CPU threads for the system under test (default 1: the arithmetic of evaluate and "
                         "replay, and no slowdown when several processes share the cores)")
    add_backend_arguments(dr)
    dr.set_defaults(func=_cmd_drive)

    tr = sub.add_parser("train", help="train the weather agent (SB3 PPO or SAC) against the system under test")
    tr.add_argument("--config", default=None, help="TOML config (default: the paper's values, configs/paper.toml)")
    tr.add_argument("--out", required=True, help="run folder (runs/NAME)")
    tr.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    tr.add_argument("--force", action="store_true", help="replace an existing run folder")
    tr.add_argument("--envs", type=int, default=None,
                    help="parallel environments (subprocesses, or Ray actors with --executor ray)")
    tr.add_argument("--steps", type=int, default=None, help="total env steps (train.total_timesteps)")
    tr.add_argument("--algorithm", choices=("ppo", "sac"), default=None,
                    help="the learner (train.algorithm): ppo (the paper's, [ppo]) or sac ([sac])")
    tr.add_argument("--n-steps", type=int, default=None, help="steps per PPO update (ppo.n_steps)")
    tr.add_argument("--episode-steps", type=int, default=None, help="steps per episode (env.episode_steps)")
    tr.add_argument("--seed", type=seed_int, default=None, help="training seed (train.seed)")
    tr.add_argument("--knobs", default=None, help="comma list of knobs the agent turns (env.knobs)")
    tr.add_argument("--disable-knobs", default=None, help="comma list of knobs held at their start (ablation)")
    tr.add_argument("--system", default=None, help="system under test (env.system)")
    tr.add_argument("--map", default=None, help="map of generated scenes (env.map)")
    tr.add_argument("--scenes", type=int, default=None, help="number of generated scenes (env.scenes)")
    tr.add_argument("--catalog", default=None, help="scene catalog file (env.catalog)")
    tr.add_argument("--quiet", action="store_true", help="no progress bar")
    add_odd_arguments(tr)
    add_backend_arguments(tr, default=None)
    add_scale_arguments(tr, "--envs")
    tr.set_defaults(func=_cmd_train)

    from genesis_rl.benchmark_cmd import add_benchmark_command
    from genesis_rl.export_cmd import add_export_command
    from genesis_rl.perception.commands import add_detector_commands, add_model_commands
    from genesis_rl.realism_cmd import add_realism_command

    add_detector_commands(sub)
    add_model_commands(sub)
    add_realism_command(sub)
    add_benchmark_command(sub)
    from genesis_rl.zoo_cmd import add_zoo_command

    add_zoo_command(sub)

    from genesis_rl.evaluation.commands import add_evaluation_commands

    add_evaluation_commands(sub)
    add_export_command(sub)

    bench = sub.add_parser("bench", help="benchmarks; prints JSON")
    bench.add_argument("what", choices=["sim", "system", "train", "campaign"],
                       help="sim: physics steps/s and frames/s; system: detector fps and closed-loop steps/s; "
                            "train: the real trainer for --updates PPO updates: rollout steps/s, seconds per "
                            "update, projected paper-schedule time; "
                            "campaign: episodes/minute per executor and worker count")
    bench.add_argument("--executors", default=None,
                       help="bench campaign: comma list of local, ray (default both); bench train: local or ray "
                            "(where the envs run, default local)")
    bench.add_argument("--workers", default="1,2", help="bench campaign: comma list of worker counts")
    bench.add_argument("--scenes", type=int, default=8, help="bench campaign: episodes per run (highway scenes)")
    bench.add_argument("--steps", type=int, default=None,
                       help="physics steps (sim, 2000), closed-loop steps (system, 200), steps per update (train, "
                            "2048)")
    bench.add_argument("--config", default=None,
                       help="bench train: the training config (default: the paper's values, configs/paper.toml)")
    bench.add_argument("--envs", type=int, default=2, help="bench train: env processes (default 2)")
    bench.add_argument("--updates", type=int, default=2, help="bench train: PPO updates to time (default 2)")
    bench.add_argument("--system", default="builtin",
                       help="system under test for 'bench system' and 'bench train' (default: builtin)")
    bench.add_argument("--frames", type=int, default=100,
                       help="frames to time per resolution (sim) or detector frames (system); default: 100")
    bench.add_argument("--no-render", action="store_true", help="physics only")
    bench.set_defaults(func=_cmd_bench)
    for choice in sub._choices_actions:  # each subcommand's own --help opens with its one-line summary
        page = sub.choices[choice.dest]
        page.description = page.description or choice.help
    add_trust_arguments(sub.choices)
    return p


def _one_line_warning(command: str, default: Any) -> Any:
    """The package's own warnings as one line naming the command (Python's format adds the file, line number
    and the source line of the warn call: noise to a user); other libraries' warnings keep their format."""
    def format_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                       line: str | None = None) -> str:
        if f"{os.sep}genesis_rl{os.sep}" in filename:
            return f"genesis-rl {command}: warning: {message}\n"
        return str(default(message, category, filename, lineno, line))

    return format_warning


def main(argv: list[str] | None = None) -> int:
    named: list[str] = []  # the subcommand, once parsed
    try:
        with interrupts_raise():  # SIGTERM cleans up as Ctrl-C does, from the first line on (signals.py)
            return _main(argv, named)
    except KeyboardInterrupt as err:  # one line, what to do next where the command knows it
        hint = resume_hint(err)
        print(" ".join(["genesis-rl", *named]) + ": interrupted" + (f"; {hint}" if hint else ""), file=sys.stderr)
        return exit_status(err)


def _main(argv: list[str] | None, named: list[str]) -> int:
    try:
        import_env_plugins()  # before the parser: a user's knobs are known to --weather and --help
    except UserInputError as err:
        print(f"genesis-rl: error: {err}", file=sys.stderr)
        return err.exit_code
    parser = build_parser()
    args = parser.parse_args(argv)
    named.append(args.command)
    default_format = warnings.formatwarning
    warnings.formatwarning = _one_line_warning(args.command, default_format)
    try:
        with trusted_for(args):  # only what this command line names is imported or unpickled
            return int(args.func(args))
    except UserInputError as err:
        print(f"genesis-rl {args.command}: error: {err}", file=sys.stderr)
        return err.exit_code
    except OSError as err:  # permission, read-only, disk full, name too long: the machine's, not a bug
        message = os_error_message(err)
        if message is None:
            raise
        print(f"genesis-rl {args.command}: error: {message}", file=sys.stderr)
        return UserInputError.exit_code
    finally:
        warnings.formatwarning = default_format


if __name__ == "__main__":
    raise SystemExit(main())
