"""``genesis-rl speed`` (``bench`` until 0.31.0): how fast this machine runs each stage.

``sim``: physics steps/s (30 vehicles, no rendering) and rendered frames/s; ``system``: detector frames/s and
closed-loop steps/s; ``train``: the real trainer's rollout steps/s and seconds per update; ``campaign``:
episodes/minute per executor and worker count; ``catalog``: seconds to save, parse and load a scene catalog;
``snapshot``: what an exact snapshot and its restore cost against an env step, per zoo member.
Each prints JSON with the machine, so that docs/benchmarks.md can name it."""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

from genesis_rl.commands.cli_args import count
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError
from genesis_rl.sim.backends import (
    catalog_or_generate,
)
from genesis_rl.sim.interface import CameraConfig, Simulation, VehicleControl
from genesis_rl.world.knobs import Weather


def _ticks_per_s(sim: Simulation, steps: int) -> float:
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.tick()
    return round(steps / (time.perf_counter() - t0), 1)


def bench_sim(physics_steps: int = 2000, frames: int = 100, render: bool = True) -> dict:
    # local, as in every command: `genesis-rl --help` builds this module's parser
    from genesis_rl.sim.lite.backend import LiteBackend, LiteSimulation
    from genesis_rl.sim.lite.scenes import generate_catalog

    scene = generate_catalog("highway", 1, 0).scenes[0]
    backend = LiteBackend()
    out: dict = {"machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
                 "python": platform.python_version(), "vehicles": len(scene.vehicles)}
    try:
        # the traffic alone: the ego on the NPC autopilot, so it stays on the road like the other 29
        with backend.create_simulation(scene, seed=0, render=False) as sim:
            assert isinstance(sim, LiteSimulation)  # LiteBackend builds LiteSimulations
            sim.traffic.drive_ego_on_autopilot()
            out["physics_steps_per_s"] = _ticks_per_s(sim, physics_steps)
        # the ego at constant throttle without steering, as in the first rows of docs/benchmarks.md: it
        # leaves the road, so each step also re-anchors it to the nearest lane
        with backend.create_simulation(scene, seed=0, render=False) as sim:
            sim.apply_ego_control(VehicleControl(throttle=0.3))
            out["physics_steps_per_s_ego_off_road"] = _ticks_per_s(sim, physics_steps)
        if render:
            weather = Weather.from_partial({"fog_density": 30, "precipitation": 40, "precipitation_deposits": 40})
            for w, h in ((320, 240), (640, 480)):
                cam = CameraConfig(width=w, height=h)
                with backend.create_simulation(scene, seed=0, camera=cam, weather=weather) as sim:
                    sim.observe()  # warm-up
                    t_tick = t_obs = 0.0
                    for _ in range(frames):
                        a = time.perf_counter()
                        sim.tick()
                        b = time.perf_counter()
                        sim.observe()
                        c = time.perf_counter()
                        t_tick, t_obs = t_tick + b - a, t_obs + c - b
                    # rendering alone (RGB + depth + boxes, weather pass included), and with the physics
                    # tick that precedes each frame in an episode (the figure of rows before 0.4.0)
                    out[f"frames_per_s_{w}x{h}"] = round(frames / t_obs, 1)
                    out[f"frames_per_s_{w}x{h}_with_physics"] = round(frames / (t_tick + t_obs), 1)
    finally:
        backend.close()
    return out


def bench_system(frames: int = 200, batch: int = 16, steps: int = 200, system: str = "builtin") -> dict:
    """Detector frames/s (batched, at its input resolution) and closed-loop steps/s (physics + render +
    detect + control, one process, default camera), with the time split per stage."""

    import numpy as np
    import torch

    from genesis_rl.loop.drive import ClosedLoop
    from genesis_rl.sim.lite.backend import LiteBackend
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.sut.system.protocol import load_system

    out: dict = {"machine": f"{platform.machine()} {platform.processor() or ''}".strip(), "cpu_count": os.cpu_count(),
                 "torch_threads": torch.get_num_threads(), "python": platform.python_version()}
    scene = generate_catalog("highway", 1, 0).scenes[0]
    sut = load_system(system)
    backend = LiteBackend()
    try:
        with backend.create_simulation(scene, seed=0) as sim:
            loop = ClosedLoop(sim, sut, backend.name, 0)
            loop.start(Weather.default())
            rgbs = []
            for _ in range(batch):
                loop.advance(Weather.default())
                assert loop.frame is not None  # set by start() and advance()
                rgbs.append(loop.frame.rgb)
            detector = getattr(sut, "detector", None)
            if detector is not None:
                stack = np.stack(rgbs)
                detector.detect_batch(stack)  # warm-up
                n = max(frames // batch, 1)
                t0 = time.perf_counter()
                for _ in range(n):
                    detector.detect_batch(stack)
                out["detector_batch"] = batch
                out["detector_input"] = list(getattr(detector, "input_size", (0, 0)))
                out["detector_frames_per_s"] = round(n * batch / (time.perf_counter() - t0), 1)
                t0 = time.perf_counter()
                for r in rgbs:
                    detector.detect(r)
                out["detector_single_frames_per_s"] = round(len(rgbs) / (time.perf_counter() - t0), 1)
            t_tick = t_obs = t_sys = 0.0
            w = Weather.default()
            for _ in range(steps):
                a = time.perf_counter()
                sim.tick()
                b = time.perf_counter()
                frame = sim.observe()
                c = time.perf_counter()
                sut.step(frame, sim.ego(), sim.step_count * sim.dt)
                d = time.perf_counter()
                t_tick, t_obs, t_sys = t_tick + b - a, t_obs + c - b, t_sys + d - c
                sim.set_weather(w)
            total = t_tick + t_obs + t_sys
            out["closed_loop_steps_per_s"] = round(steps / total, 1)
            out["ms_per_step"] = {"physics": round(1e3 * t_tick / steps, 2), "render": round(1e3 * t_obs / steps, 2),
                                  "system": round(1e3 * t_sys / steps, 2)}
    finally:
        backend.close()
    return out


def bench_train(config: str | None = None, envs: int = 2, updates: int = 2, n_steps: int | None = None,
                system: str | None = None, executor: str = "local") -> dict:
    """The real trainer (``genesis-rl train``, checkpoints and all) for ``updates`` PPO updates of the paper's
    config (``config``; None: the paper's values) with ``envs`` env processes (``executor`` ray: Ray actors):
    env steps/s while collecting rollouts, seconds per PPO update, the start-up (envs built before the first
    step), and the paper schedule's projected wall time (40,960 steps = 20 updates of 2048) from them."""
    import tempfile
    from dataclasses import replace
    from pathlib import Path

    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    from genesis_rl.distributed.settings import ExecutorSettings
    from genesis_rl.training.config import load_run_config
    from genesis_rl.training.train import train

    marks: list[tuple[str, float]] = []

    class Timer(BaseCallback):
        def _on_rollout_start(self) -> None:
            marks.append(("rollout_start", time.perf_counter()))

        def _on_rollout_end(self) -> None:
            marks.append(("rollout_end", time.perf_counter()))

        def _on_step(self) -> bool:
            return True

    overrides: dict[str, dict] = {"train": {"envs": envs}}
    if n_steps is not None:
        overrides["ppo"] = {"n_steps": n_steps}
    if system is not None:
        overrides["env"] = {"system": system}
    cfg = load_run_config(config, overrides)
    per_update = cfg.ppo.n_steps
    cfg = replace(cfg, train=replace(cfg.train, total_timesteps=per_update * updates))
    threads = torch.get_num_threads()
    with tempfile.TemporaryDirectory(prefix="genesis-rl-bench-") as tmp:
        t0 = time.perf_counter()
        train(cfg, Path(tmp) / "run", progress=False, callbacks=[Timer()], scale=ExecutorSettings(executor, envs))
        total = time.perf_counter() - t0
    torch.set_num_threads(threads)
    starts = [t for k, t in marks if k == "rollout_start"]
    ends = [t for k, t in marks if k == "rollout_end"]
    rollout = sum(e - s for s, e in zip(starts, ends, strict=True))
    # an update runs from a rollout's end to the next rollout's start (checkpoint included); the last one
    # from the last rollout's end to the end of train()
    update = sum(s - e for e, s in zip(ends, [*starts[1:], t0 + total], strict=True))
    setup = starts[0] - t0
    steps_per_s = per_update * updates / rollout
    update_s = update / updates
    paper_updates = 40960 // 2048
    return {
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(), "cpu_count": os.cpu_count(),
        "torch_threads": threads, "system": cfg.env.system, "executor": executor, "envs": envs,
        "n_steps": per_update,
        "updates": updates, "obs": [cfg.env.obs_width, cfg.env.obs_height],
        "setup_seconds": round(setup, 1),
        "rollout_env_steps_per_s": round(steps_per_s, 2),
        "seconds_per_update": round(update_s, 2),
        "projected_paper_schedule_minutes": round((setup + 40960 / steps_per_s
                                                   + paper_updates * update_s * 2048 / per_update) / 60.0, 2),
    }


def bench_campaign(scenes: int = 8, steps: int = 256, executors: tuple[str, ...] = ("local", "ray"),
                   workers: tuple[int, ...] = (1, 2), system: str = "builtin") -> dict:
    """Episodes per minute of one campaign (sunny weather, ``scenes`` highway scenes of ``steps`` steps) per
    executor and worker count, the summaries checked equal; Ray's start-up is timed apart from the campaign,
    and its cost per episode is the difference to the local executor with as many workers."""
    import json
    import tempfile
    from contextlib import ExitStack
    from pathlib import Path

    from genesis_rl.campaigns.campaign import CampaignSpec, run_campaign
    from genesis_rl.distributed.settings import ExecutorSettings
    from genesis_rl.sim.lite.scenes import generate_catalog

    out: dict = {"machine": f"{platform.machine()} {platform.processor() or ''}".strip(), "cpu_count": os.cpu_count(),
                 "scenes": scenes, "steps": steps, "system": system, "runs": []}
    with tempfile.TemporaryDirectory(prefix="genesis-rl-bench-") as tmp:
        catalog = Path(tmp) / "highway.json"
        generate_catalog("highway", max(scenes, 12), 0).save(catalog)
        spec = CampaignSpec(policies=("sunny",), catalog=str(catalog), scenes=scenes, seed=0, steps=steps,
                            env={"system": system})
        with ExitStack() as stack:
            if "ray" in executors:
                from genesis_rl.distributed.ray_cluster import ray_session

                t0 = time.perf_counter()
                stack.enter_context(ray_session(None, max(workers)))  # campaigns reuse it; timed apart
                out["ray_init_seconds"] = round(time.perf_counter() - t0, 2)
            first: str | None = None
            for kind in executors:
                for n in workers:
                    folder = Path(tmp) / f"{kind}_{n}"
                    t0 = time.perf_counter()
                    summary = run_campaign(spec, folder, progress=False, executor=ExecutorSettings(kind, n))
                    seconds = time.perf_counter() - t0
                    body = json.dumps(summary.to_json()["policies"], sort_keys=True)
                    first = first or body
                    sent = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()
                               and p.parts[len(folder.parts)] in ("episodes", "steps", "frames", "records"))
                    out["runs"].append({"executor": kind, "workers": n, "seconds": round(seconds, 1),
                                        "episodes_per_minute": round(60.0 * scenes / seconds, 2),
                                        "result_bytes_per_episode": sent // scenes,
                                        "same_summary_as_first": body == first})
    local = {r["workers"]: r["seconds"] for r in out["runs"] if r["executor"] == "local"}
    for r in out["runs"]:
        if r["executor"] == "ray" and r["workers"] in local:
            r["ray_overhead_seconds_per_episode"] = round((r["seconds"] - local[r["workers"]]) * r["workers"] / scenes,
                                                          2)
    return out


def bench_catalog(scenes: int = 1200, repeats: int = 5) -> dict:
    """CPU seconds (the best of ``repeats``) to save a catalog, read its JSON, check it against the schema and load
    it with the backend's checks, for the free-flow highway and the mixed urban traffic of ``scenes`` scenes.
    Every env pays the load once (each campaign worker and training env), the estimate and the campaign
    runner the save. CPU time, not wall time, so that other work on the machine moves it less."""
    import tempfile
    from functools import partial
    from pathlib import Path

    from genesis_rl.core.parsing import read_json
    from genesis_rl.sim.backends import load_catalog
    from genesis_rl.world.scenes.catalog import parse_catalog

    def _parse_file(path: Path) -> object:
        return parse_catalog(read_json(path))

    def best(fn: Callable[[], object]) -> float:
        times = []
        for _ in range(repeats):
            start = time.process_time()
            fn()
            times.append(time.process_time() - start)
        return round(min(times), 3)

    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="genesis-rl-bench-") as tmp:
        for name, map_name, traffic in (("highway_free_flow", "highway", "free_flow"), ("urban", "urban", "mixed")):
            catalog = catalog_or_generate(None, map_name, scenes, 0, traffic=traffic)
            path = Path(tmp) / f"{name}.json"
            out[name] = {"scenes": scenes, "vehicles": sum(len(s.vehicles) for s in catalog.scenes),
                         "save_s": best(partial(catalog.save, path)),
                         "read_json_s": best(partial(read_json, path)),
                         "parse_s": best(partial(_parse_file, path)),
                         "load_s": best(partial(load_catalog, path)),
                         "bytes": path.stat().st_size}
    return {"what": "catalog", "cpu_seconds_best_of": repeats, **out}



#: the members ``speed snapshot`` times by default: two urban weather members (two detectors), two highway timing
#: members (a latency queue, a stalling camera), and the real-photo detector's
SNAPSHOT_MEMBERS = ("low_sun", "glare_blind", "latency_braking", "stall_braking", "coco_low_sun")


def bench_snapshot(members: tuple[str, ...] = SNAPSHOT_MEMBERS, steps: int = 200, repeats: int = 50) -> dict:
    """Per member: milliseconds per env step (render, detect, control, rules), per ``GenesisEnv.snapshot`` and per
    ``restore`` (the best of ``repeats`` each, mid-episode), and a snapshot's cost in steps: what returning to a
    state costs Go-Explore against replaying the steps that reached it."""
    import numpy as np

    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv
    from genesis_rl.sut.zoo.members import env_settings, zoo_member

    out: dict[str, dict] = {}
    for name in members:
        env = GenesisEnv(EnvConfig(**{**env_settings(zoo_member(name)), "scenes": 2, "episode_steps": steps + 1}))
        try:
            action = np.zeros(env.mapper.action_dim, np.float32)
            env.reset(options={"scene": 0, "episode_seed": 0})
            t0 = time.perf_counter()
            for _ in range(steps):
                env.step(action)
            step_ms = (time.perf_counter() - t0) / steps * 1e3
            snaps, restores = [], []
            for _ in range(repeats):
                a = time.perf_counter()
                snap = env.snapshot()
                b = time.perf_counter()
                env.restore(snap)
                snaps.append(b - a)
                restores.append(time.perf_counter() - b)
            out[name] = {"step_ms": round(step_ms, 2), "snapshot_ms": round(min(snaps) * 1e3, 2),
                         "restore_ms": round(min(restores) * 1e3, 2),
                         "snapshot_and_restore_in_steps": round((min(snaps) + min(restores)) * 1e3 / step_ms, 3)}
        finally:
            env.close()
    return {"what": "snapshot", "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            "steps_timed": steps, "best_of": repeats, **out}


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``speed`` command's flags (also answering to its old name, ``bench``)."""
    p = sub.add_parser("speed", aliases=["bench"],
                       help="how fast the simulator, the system, training and campaigns run here; JSON")
    p.add_argument("what", choices=["sim", "system", "train", "campaign", "catalog", "snapshot"],
                   help="sim: physics steps/s and frames/s; system: detector fps and closed-loop steps/s; "
                        "train: the real trainer for --updates PPO updates: rollout steps/s, seconds per "
                        "update, projected paper-schedule time; "
                        "campaign: episodes/minute per executor and worker count; catalog: seconds to save, "
                        "parse and load a scene catalog (every env pays the load); snapshot: an exact snapshot's "
                        "and restore's cost against an env step, per zoo member")
    p.add_argument("--executors", default=None,
                   help="speed campaign: comma list of local, ray (default both); speed train: local or ray "
                        "(where the envs run, default local)")
    p.add_argument("--workers", default="1,2", help="speed campaign: comma list of worker counts")
    p.add_argument("--scenes", type=int, default=None,
                   help="speed campaign: episodes per run (highway scenes, default 8); speed catalog: scenes per "
                        "catalog (default 1200, as the estimate's free-flow highway catalog)")
    p.add_argument("--steps", type=int, default=None,
                   help="physics steps (sim, 2000), closed-loop steps (system, 200), steps per update (train, "
                        "2048), env steps timed before the snapshots (snapshot, 200)")
    p.add_argument("--config", default=None,
                   help="speed train: the training config (default: the paper's values, configs/paper.toml)")
    p.add_argument("--envs", type=int, default=2, help="speed train: env processes (default 2)")
    p.add_argument("--updates", type=int, default=2, help="speed train: PPO updates to time (default 2)")
    p.add_argument("--system", default="builtin",
                   help="system under test for 'speed system' and 'speed train' (default: builtin)")
    p.add_argument("--frames", type=int, action=count(1, limits.FRAMES), default=100,
                   help="frames to time per resolution (sim) or detector frames (system); default: 100")
    p.add_argument("--no-render", action="store_true", help="physics only")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    status = _run(args)
    if args.command == "bench":  # after the figures: a refusal stays one line
        print("genesis-rl: 'bench' is now 'genesis-rl speed' (not to be confused with 'benchmark'); the old name "
              "works until 0.31.0", file=sys.stderr)
    return status


def _run(args: argparse.Namespace) -> int:
    if args.what == "catalog":

        scenes = 1200 if args.scenes is None else args.scenes
        if not 1 <= scenes <= 5000:
            raise UserInputError(f"--scenes = {scenes} must be in 1..5000")
        print(json.dumps(bench_catalog(scenes=scenes), indent=2))
        return 0
    steps = args.steps if args.steps is not None else {"sim": 2000, "system": 200, "train": 2048,
                                                       "campaign": 256, "snapshot": 200}[args.what]
    least = 2 if args.what == "train" else 1  # a PPO update needs two steps
    if steps < least:
        raise UserInputError(f"--steps = {steps} must be >= {least}")
    limits.SIM_STEPS.check(steps, "--steps")

    if args.what == "campaign":
        scenes = 8 if args.scenes is None else args.scenes
        executors = tuple(t.strip() for t in (args.executors or "local,ray").split(","))
        bad = [e for e in executors if e not in ("local", "ray")]  # an empty item (ray,,local) is a typo too
        if bad or not executors or len(set(executors)) < len(executors):
            raise UserInputError(f"--executors {args.executors!r}; allowed: a comma list of local, ray (each once, "
                                 "no empty items)")
        counts = limits.count_list(args.workers, "--workers", limits.WORKERS)  # 1,,2 is refused
        if not 1 <= scenes <= 500:
            raise UserInputError(f"--scenes = {scenes} must be in 1..500")
        print(json.dumps(bench_campaign(scenes=scenes, steps=steps, executors=executors, workers=counts,
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
    if args.what == "snapshot":
        print(json.dumps(bench_snapshot(steps=steps), indent=2))
        return 0
    if args.what == "system":
        print(json.dumps(bench_system(frames=args.frames, steps=steps, system=args.system), indent=2))
        return 0
    print(json.dumps(bench_sim(physics_steps=steps, frames=args.frames, render=not args.no_render), indent=2))
    return 0
