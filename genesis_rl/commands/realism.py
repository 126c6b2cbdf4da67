"""``genesis-rl realism``: does a detector trained on photographs believe lite's cars? Recall by distance and
false positives on held-out renders, and the closed loop's safety at clear noon (docs/realism.md).

It lives outside ``perception`` because it drives systems and campaigns, which themselves use perception."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from genesis_rl.commands.cli_args import SEED
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError


def _parse_sizes(text: str) -> tuple[tuple[int, int], ...]:
    sizes = []
    for item in (t.strip() for t in text.split(",")):
        try:
            w, h = (int(v) for v in item.lower().split("x"))
        except ValueError:
            raise UserInputError(f"--sizes: '{item}' is not WIDTHxHEIGHT (e.g. 320x240,640x480)") from None
        if not (64 <= w <= 1920 and 48 <= h <= 1440):
            raise UserInputError(f"--sizes: {w}x{h} is outside 64x48..1920x1440")
        sizes.append((w, h))
    if len(sizes) > limits.MAX_LIST_ITEMS:
        raise UserInputError(f"--sizes lists {len(sizes)} sizes; allowed: at most {limits.MAX_LIST_ITEMS}")
    return tuple(sizes)


def run(args: argparse.Namespace) -> int:
    from genesis_rl.core.files.io_utils import atomic_write_json, ensure_writable
    from genesis_rl.core.files.output_paths import check_folder_output, check_inputs
    from genesis_rl.sim.lite.maps import MAP_NAMES
    from genesis_rl.sut.perception import realism
    from genesis_rl.sut.system.protocol import WEIGHTED_SYSTEMS, load_system

    maps = tuple(m.strip() for m in args.maps.split(",") if m.strip())
    bad = [m for m in maps if m not in MAP_NAMES]
    if bad or not maps:
        raise UserInputError(f"--maps: unknown map(s) {bad or '(none given)'}; allowed: {', '.join(MAP_NAMES)}")
    sizes = _parse_sizes(args.sizes)
    for flag, value, lo, hi in (("--scenes", args.scenes, 1, 500), ("--frames-per-scene", args.frames_per_scene, 1, 16),
                                ("--closed-loop-scenes", args.closed_loop_scenes, 0, 500),
                                ("--closed-loop-steps", args.closed_loop_steps, 1, 100000),
                                ("--workers", args.workers, 1, limits.WORKERS.value())):
        if not lo <= value <= hi:
            raise UserInputError(f"{flag} = {value} must be in {lo}..{hi}")
    if args.weights and args.system not in WEIGHTED_SYSTEMS:
        raise UserInputError(f"--weights applies to --system {', '.join(WEIGHTED_SYSTEMS)} only")
    spec = realism.RealismSpec(maps=maps, sizes=sizes, scenes=args.scenes, frames_per_scene=args.frames_per_scene,
                               seed=args.seed, closed_loop_scenes=args.closed_loop_scenes,
                               closed_loop_steps=args.closed_loop_steps)
    out = Path(args.out)
    check_folder_output(args.out)
    names = ["realism.json", *(f"realism_sheet_{m}.png" for m in maps)]
    check_inputs(out, [args.weights], folder=True, files=names)
    for name in names:
        ensure_writable(out / name, args.force)
    kwargs: dict = {"weights": args.weights} if args.weights else {}
    if args.image_size is not None:
        if args.system != "coco":
            raise UserInputError("--image-size applies to --system coco only")
        kwargs["image_size"] = args.image_size
    system = load_system(args.system, **kwargs)
    detector = getattr(system, "detector", None)
    if detector is None or not hasattr(detector, "detect_batch"):
        raise UserInputError(f"--system {args.system} has no detector to score (realism scores a system's "
                             f"`detector.detect_batch`); allowed: builtin, coco, yolo or a plug-in with one")
    t0 = time.perf_counter()
    views = []
    for map_name in maps:
        largest = max(sizes, key=lambda s: s[0] * s[1])
        for size in sizes:
            data = realism.render_views(spec, map_name, size, progress=not args.quiet)
            score = realism.score_views(detector.detect_batch, data, spec, map_name)
            views.append(score.as_dict())
            if not args.quiet:
                row = score.as_dict()
                print(f"[realism] {map_name} {size[0]}x{size[1]}: recall within 20 m {row['within_20m']['recall']}, "
                      f"within 30 m {row['within_30m']['recall']}, {row['false_positives_per_frame']} false "
                      f"positives per frame", flush=True)
            if size == largest:
                out.mkdir(parents=True, exist_ok=True)
                realism.contact_sheet(data, score, None, out / f"realism_sheet_{map_name}.png")
    closed: dict | None = None
    if spec.closed_loop_scenes:
        from genesis_rl.campaigns.campaign import CampaignSpec, env_settings_for, run_campaign
        from genesis_rl.distributed.settings import ExecutorSettings

        env = env_settings_for(None, None, args.system, args.weights)
        if args.image_size is not None:
            env["system_kwargs"] = {**env.get("system_kwargs", {}), "image_size": args.image_size}
        campaign = CampaignSpec(policies=("sunny",), map="highway", scenes=spec.closed_loop_scenes,
                                seed=spec.closed_loop_seed, steps=spec.closed_loop_steps, env=env)
        summary = run_campaign(campaign, out / "closed_loop", force=args.force, resume=args.resume,
                               progress=not args.quiet, executor=ExecutorSettings(workers=args.workers))
        sunny = summary.policies["sunny"]
        n, crashed = sunny.episodes, sunny.episodes_with_collision
        closed = {"map": "highway", "weather": "clear_noon", "scenes": n, "seed": spec.closed_loop_seed,
                  "steps": spec.closed_loop_steps, "episodes_with_collision": crashed,
                  "collision_free_share": round((n - crashed) / n, 4), "campaign": str(out / "closed_loop")}
    result = {"schema": "genesis-rl/realism", "version": 1, "system": system.identity(),
              "spec": realism.spec_dict(spec), "views": views, "closed_loop": closed,
              "seconds": round(time.perf_counter() - t0, 1)}
    atomic_write_json(out / "realism.json", result, indent=2)
    print(json.dumps({"out": str(out), "views": [{k: v[k] for k in ("map", "size", "within_20m", "within_30m",
                                                                     "false_positives_per_frame")} for v in views],
                      "closed_loop": closed}, indent=1 if args.quiet else 2))
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    rp = subparsers.add_parser("realism", help="does a photo-trained detector believe lite's cars? recall by "
                                               "distance, false positives, closed-loop safety; JSON + contact sheets")
    rp.add_argument("--system", default="coco", help="system whose detector is scored and which drives the "
                                                     "closed loop: coco (default), builtin, yolo, or a plug-in")
    rp.add_argument("--weights", default=None, help="its weights (builtin/yolo: a file; coco: a model folder)")
    rp.add_argument("--image-size", type=int, default=None,
                    help="coco: the detector's input long side in px, a multiple of 32 (default 416, darknet's; "
                         "640 runs a 640x480 frame at its own size)")
    rp.add_argument("--maps", default="highway,urban", help="comma-separated maps (default: highway,urban)")
    rp.add_argument("--sizes", default="320x240,640x480", help="frame sizes (default: 320x240,640x480)")
    rp.add_argument("--scenes", type=int, default=60, help="held-out scenes per map (default 60)")
    rp.add_argument("--frames-per-scene", type=int, default=2, help="frames per scene (default 2)")
    rp.add_argument("--seed", type=int, action=SEED, default=7, help="seed of the traffic states (default 7)")
    rp.add_argument("--closed-loop-scenes", type=int, default=50,
                    help="highway scenes driven at clear noon by the system (default 50; 0 skips)")
    rp.add_argument("--closed-loop-steps", type=int, default=512, help="steps per closed-loop episode (default 512)")
    rp.add_argument("--workers", type=int, default=2, help="processes for the closed loop (default 2)")
    rp.add_argument("--out", default="out/realism", help="output folder (default: out/realism)")
    rp.add_argument("--force", action="store_true", help="overwrite existing outputs")
    rp.add_argument("--resume", action="store_true", help="resume an interrupted closed-loop campaign")
    rp.add_argument("--quiet", action="store_true", help="no progress bars")
    rp.set_defaults(func=run)
    return rp
