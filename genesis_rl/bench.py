"""``genesis-rl bench sim``: physics steps/s (30 vehicles, no rendering) and rendered frames/s."""

from __future__ import annotations

import platform
import time

from genesis_rl.knobs import Weather
from genesis_rl.lite.backend import LiteBackend
from genesis_rl.scenes.lite_generator import generate_catalog
from genesis_rl.sim.interface import CameraConfig, VehicleControl


def bench_sim(physics_steps: int = 2000, frames: int = 100, render: bool = True) -> dict:
    scene = generate_catalog("highway", 1, 0).scenes[0]
    backend = LiteBackend()
    out: dict = {"machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
                 "python": platform.python_version(), "vehicles": len(scene.vehicles)}
    try:
        with backend.create_simulation(scene, seed=0, render=False) as sim:
            sim.apply_ego_control(VehicleControl(throttle=0.3))
            t0 = time.perf_counter()
            for _ in range(physics_steps):
                sim.tick()
            out["physics_steps_per_s"] = round(physics_steps / (time.perf_counter() - t0), 1)
        if render:
            weather = Weather.from_partial({"fog_density": 30, "precipitation": 40, "precipitation_deposits": 40})
            for w, h in ((320, 240), (640, 480)):
                cam = CameraConfig(width=w, height=h)
                with backend.create_simulation(scene, seed=0, camera=cam, weather=weather) as sim:
                    sim.observe()  # warm-up
                    t0 = time.perf_counter()
                    for _ in range(frames):
                        sim.tick()
                        sim.observe()
                    out[f"frames_per_s_{w}x{h}"] = round(frames / (time.perf_counter() - t0), 1)
    finally:
        backend.close()
    return out
