"""Closed-loop driving: the system under test drives one scene under a weather schedule.

Per step: observe (camera) -> system (detect, localise, control) -> apply control -> tick -> record. The
step record (``step_record.StepRecord``) is what later stages (rulebook, env, campaigns) read; its flat
columns are what the telemetry Parquet holds.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.core.files.io_utils import atomic_write
from genesis_rl.loop.rules.rulebook import ProximityRule
from genesis_rl.sim.geometry import frame_iou, in_view, iou_matrix
from genesis_rl.sim.interface import Backend, CameraConfig, SensorFrame, Simulation
from genesis_rl.sut.system.protocol import EpisodeContext, SystemOutput, SystemUnderTest
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.odd.conditions import Conditions, conditions_model
from genesis_rl.world.scenes.catalog import Scene
from genesis_rl.world.step_record import (
    CollisionStep,
    EgoStep,
    LeadStep,
    PerceptionStep,
    StepRecord,
    to_rows,
)


def episode_context(sim: Simulation, backend_name: str, seed: int) -> EpisodeContext:
    """What the system may know before the episode: map, its own start, camera, time step."""
    scene: Scene = sim.scene  # type: ignore[attr-defined]
    ego = scene.vehicles[0]
    return EpisodeContext(
        backend=backend_name,
        map_name=scene.map,
        road_map=getattr(sim, "map", None),
        camera=sim.camera,  # type: ignore[attr-defined]
        dt=sim.dt,
        seed=seed,
        ego_lane=ego.lane,
        ego_s=ego.s,
        ego_next_lane=ego.next_lane,
        signal_time_offset=scene.signal_offset,
        extras=sim.context_extras(),
    )


def step_record(step: int, sim: Simulation, frame: SensorFrame, out: SystemOutput, collisions: list,
                weather: Weather, ego_speed: float, knob_names: Sequence[str],
                conditions: Conditions | None = None) -> StepRecord:
    """The record of one step: the state after the step's tick, the frame observed then and the system's
    answer to it; collisions are those of that tick; ``conditions`` those of the weather seen from the ego."""
    lead = sim.lead()
    dets = np.array([d.xyxy for d in out.detections], np.float64).reshape(-1, 4)
    iou, _ = frame_iou(frame.boxes, dets)
    ego_hits = [c for c in collisions if 0 in (c.vehicle_a, c.vehicle_b)]
    c = out.control
    nan = float("nan")
    return StepRecord(
        step=step,
        time_s=round(step * sim.dt, 3),
        ego=EgoStep(ego_speed, c.throttle, c.brake, c.steer, out.status),
        lead=LeadStep(
            vehicle_id=-1 if lead is None else lead.vehicle_id,
            true_distance=nan if lead is None else lead.gap,
            speed=nan if lead is None else lead.speed,
            perceived_distance=nan if out.lead_distance is None else out.lead_distance,
            detected=_lead_detected(lead, frame, dets),
        ),
        perception=PerceptionStep(
            n_detections=len(out.detections),
            n_in_view=sum(1 for b in frame.boxes if in_view(b)),
            iou=iou,
            detections=tuple(d.recorded() for d in out.detections),
            gt_boxes=tuple(b.recorded() for b in frame.boxes),
        ),
        collision=CollisionStep(
            collided=bool(ego_hits),
            speed=max((c.speed_a if c.vehicle_a == 0 else c.speed_b for c in ego_hits), default=0.0),
            other_id=-1 if not ego_hits else (ego_hits[0].vehicle_b if ego_hits[0].vehicle_a == 0
                                              else ego_hits[0].vehicle_a),
        ),
        knobs={k: float(weather[k]) for k in knob_names},
        conditions=conditions,
    )


def _lead_detected(lead: Any, frame: SensorFrame, dets: np.ndarray) -> bool | None:
    """Whether the true lead vehicle's box is matched by a detection (IoU >= 0.3); None when it is not in
    the image (hidden, out of frame or no lead)."""
    if lead is None:
        return None
    box = next((b for b in frame.boxes if b.vehicle_id == lead.vehicle_id), None)
    if box is None:
        return None
    if len(dets) == 0:
        return False
    return bool(iou_matrix(np.array([box.xyxy], np.float64), dets).max() >= 0.3)


@dataclass
class EpisodeResult:
    records: list[StepRecord]
    frames: list[np.ndarray] = field(default_factory=list)
    identity: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return summarize(self.records)


def summarize(records: Sequence[StepRecord]) -> dict[str, Any]:
    """Episode figures: collisions, proximity (the paper's 5 m proximity rule), gaps, IoU, distance driven."""
    proximity = ProximityRule()
    if not records:
        return {"steps": 0}
    speed = np.array([r.ego.speed for r in records])
    gap = np.array([r.lead.true_distance for r in records], float)
    hits = [r for r in records if r.collision.collided]
    dt = records[1].time_s - records[0].time_s if len(records) > 1 else 0.05
    near = np.nan_to_num(gap, nan=np.inf) < proximity.distance
    return {
        "steps": len(records),
        "collisions": len(hits),
        "first_collision_step": hits[0].step if hits else None,
        "collision_speed": round(float(hits[0].collision.speed), 3) if hits else 0.0,
        "proximity_steps": int(near.sum()),
        "proximity_violation": round(proximity.violation(records), 3),
        "min_true_gap": round(float(np.nanmin(gap)), 3) if np.isfinite(gap).any() else None,
        "mean_speed": round(float(speed.mean()), 3),
        "distance_m": round(float(speed.sum() * dt), 2),
        "mean_iou": round(float(np.mean([r.iou for r in records])), 4),
    }


class ClosedLoop:
    """The step template shared by ``drive``, the Gymnasium env and campaigns.

    ``start`` observes the first frame and lets the system choose its first control; each ``advance``
    then sets the step's weather, ticks (the ego moves under the last control), observes, lets the
    system choose the next control, and returns the step record (collisions are those of this tick).
    """

    def __init__(self, sim: Simulation, system: SystemUnderTest, backend_name: str, seed: int,
                 reset_system: bool = True) -> None:
        """``reset_system`` False: the system is already mid-episode (a restored snapshot), not reset."""
        self.sim = sim
        self.system = system
        self.knob_names = list(KNOBS)
        self.conditions_model = conditions_model(backend_name)
        if reset_system:
            system.reset(episode_context(sim, backend_name, seed))
        self.frame: SensorFrame | None = None
        self.output: SystemOutput | None = None

    def _perceive(self) -> None:
        sim = self.sim
        self.frame = sim.observe()
        self.ego = sim.ego()
        self.output = self.system.step(self.frame, self.ego, sim.step_count * sim.dt)
        sim.apply_ego_control(self.output.control)

    def start(self, weather: Weather) -> None:
        self.sim.set_weather(weather)
        self._perceive()

    def advance(self, weather: Weather) -> StepRecord:
        sim = self.sim
        sim.set_weather(weather)
        tick = sim.tick()
        self._perceive()
        assert self.frame is not None and self.output is not None
        conditions = self.conditions_model.conditions(weather, self.heading_deg)
        return step_record(sim.step_count, sim, self.frame, self.output, tick.collisions, weather,
                           self.ego.speed, self.knob_names, conditions)

    @property
    def heading_deg(self) -> float:
        """The ego's (and its camera's) heading, counter-clockwise from east [deg]."""
        return math.degrees(self.ego.yaw)


def run_episode(
    backend: Backend,
    scene: Scene,
    system: SystemUnderTest,
    weather_at: Callable[[int], Weather],
    steps: int,
    seed: int,
    camera: CameraConfig | None = None,
    frame_hook: Callable[[int, SensorFrame, SystemOutput, StepRecord], None] | None = None,
    progress: bool = False,
    stop_on_collision: bool = False,
) -> EpisodeResult:
    """Drive ``scene`` for ``steps`` steps; ``weather_at(k)`` is the weather of step k (0-based), set
    before the tick that step k makes."""
    from tqdm import tqdm

    records: list[StepRecord] = []
    with backend.create_simulation(scene, seed=seed, weather=weather_at(0), camera=camera) as sim:
        loop = ClosedLoop(sim, system, backend.name, seed)
        loop.start(weather_at(0))
        for k in tqdm(range(steps), desc=f"scene {scene.index}", disable=not progress, unit="step"):
            rec = loop.advance(weather_at(k))
            records.append(rec)
            if frame_hook is not None:
                assert loop.frame is not None and loop.output is not None
                frame_hook(k, loop.frame, loop.output, rec)
            if stop_on_collision and rec.collision.collided:
                break
    return EpisodeResult(records, identity=system.identity())


def write_telemetry(path: Path, records: Sequence[StepRecord]) -> None:
    """Step records as Parquet (their flat columns, ``StepRecord.to_row``), written atomically."""
    import pyarrow as pa  # local: start-up cost of pyarrow for commands that never write telemetry
    import pyarrow.parquet as pq

    table = pa.Table.from_pylist(to_rows(records))
    atomic_write(Path(path), lambda p: pq.write_table(table, p, compression="zstd"))
