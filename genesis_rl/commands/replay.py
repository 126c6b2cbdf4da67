"""``genesis-rl replay``: re-run an edge-case record, check its violations, write a GIF."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

from genesis_rl.commands.cli_args import count
from genesis_rl.core.errors import UserInputError

if TYPE_CHECKING:
    pass



def _explain_platform(recorded: dict | None, now: dict) -> None:
    """Say when the record was made where float math differs in its last bits (provenance.numeric_platform)."""
    if recorded is None:
        print("genesis-rl replay: the record does not name the machine that made it (records before genesis-rl "
              "0.8.0); a CPU with other vector extensions (AVX2 against AVX-512) or another numpy or torch "
              f"differs in the last bits of float math; this machine: {now}", flush=True)
    elif recorded != now:
        diff = {k: (recorded.get(k), v) for k, v in now.items() if recorded.get(k) != v}
        print("genesis-rl replay: the record was made on a machine whose float math differs in its last bits "
              f"from this one's (recorded, here): {diff}; replay it on such a machine to reproduce it bit for "
              "bit", flush=True)


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``replay`` command's flags."""
    p = sub.add_parser("replay", help="re-run an edge-case record; check its violations; write a GIF")
    p.add_argument("record", help="edge-case record (CAMPAIGN/records/*.json)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--weights", default=None, help="detector weights, when the recorded file has moved")
    p.add_argument("--gif-seconds", type=int, action=count(0), default=6,
                   help="seconds before the collision in the GIF (0: all)")
    p.add_argument("--no-gif", action="store_true", help="skip the animation")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--world-seed", type=int, default=None,
                   help="play the recorded schedule in another world (the traffic's behaviour, the camera's noise, "
                        "the system's draws), as benchmark re-runs do (OUT/reproductions/ names their seeds); "
                        "default: the recorded world, and the replay checks that it reproduces")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from genesis_rl.campaigns.records import load_record, recorded_world_seed, replay_record
    from genesis_rl.core.files.io_utils import atomic_write_json, ensure_writable
    from genesis_rl.loop.drive import write_telemetry
    from genesis_rl.loop.frames import annotate_frame, write_gif

    if args.world_seed is not None and not 0 <= args.world_seed < 2**63:
        raise UserInputError(f"--world-seed = {args.world_seed}; allowed: an integer in 0..2**63-1")
    rec = load_record(args.record)
    spec = str(rec["system"].get("spec", ""))
    if args.weights and spec in ("blind", "oracle"):  # they read no weights; a plug-in may
        raise UserInputError(f"--weights applies to records of --system builtin, yolo or a plug-in that takes "
                             f"weights; this record's system is '{spec}'")
    from genesis_rl.core.files.output_paths import check_folder_output, check_inputs

    out = Path(args.out)
    check_folder_output(args.out)
    names = ("replay.json", "telemetry.parquet", "replay.gif")
    check_inputs(out, [args.record, args.weights], folder=True, files=names)
    for name in names:
        ensure_writable(out / name, args.force)
    result = replay_record(rec, weights=args.weights, progress=not args.quiet, keep_frames=not args.no_gif,
                           world_seed=args.world_seed)
    write_telemetry(out / "telemetry.parquet", result["records"])
    if not args.no_gif:
        hit = next((i for i, r in enumerate(result["records"]) if r.collision.collided), len(result["records"]) - 1)
        lo = max(0, hit - args.gif_seconds * 20) if args.gif_seconds else 0
        frames = [annotate_frame(result["frames"][i], result["records"][i])
                  for i in range(lo, min(len(result["frames"]), hit + 20), 2)]
        write_gif(out / "replay.gif", frames, fps=10)
    first = next((r.step for r in result["records"] if r.collision.collided), None)
    if args.world_seed is None:
        report = {"record": str(args.record), "reproduced": result["reproduced"],
                  "steps_identical": result["steps_identical"], "violations": result["violations"],
                  "render_version": result["render_version"],
                  "recorded_render_version": result["recorded_render_version"],
                  "recorded_violations": result["recorded_violations"], "steps": len(result["records"]),
                  "first_collision_step": first}
    else:  # another world: nothing to reproduce, only what happened there
        report = {"record": str(args.record), "world_seed": args.world_seed,
                  "recorded_world_seed": recorded_world_seed(rec), "violations": result["violations"],
                  "recorded_violations": result["recorded_violations"], "steps": len(result["records"]),
                  "first_collision_step": first,
                  "recorded_first_collision_step": (rec.get("summary") or {}).get("first_collision_step")}
    atomic_write_json(out / "replay.json", report, indent=2)
    print(json.dumps(report, indent=2))
    if args.world_seed is None and not result["reproduced"]:
        same_violations = set(result["violations"]) == set(result["recorded_violations"]) and all(
            math.isclose(result["violations"][k], v, rel_tol=1e-9, abs_tol=1e-9)
            for k, v in result["recorded_violations"].items())
        if same_violations:
            print("genesis-rl replay: the violations are the recorded ones, but the per-step telemetry is not "
                  "(its digest differs: a detection score or distance changed somewhere)", flush=True)
            _explain_platform(result["recorded_platform"], result["platform"])
        else:
            print("genesis-rl replay: the replayed violations differ from the recorded ones", flush=True)
        from genesis_rl import __version__

        recorded_version = rec.get("package_version")
        if result["recorded_render_version"] != result["render_version"]:
            print(f"genesis-rl replay: the record was made by lite renderer version "
                  f"{result['recorded_render_version']} (genesis-rl {recorded_version}), this is "
                  f"version {result['render_version']}: the frames differ slightly, so the detector may "
                  f"see the scene differently; replay with the recorded genesis-rl version to reproduce it",
                  flush=True)
        elif recorded_version != __version__:
            print(f"genesis-rl replay: the record was made by genesis-rl {recorded_version}, this is "
                  f"{__version__}; replay it with the recorded version to reproduce it exactly", flush=True)
        return 1
    return 0
