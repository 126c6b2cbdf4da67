"""An episode of ``GenesisEnv`` frozen at one step, to be returned to (``GenesisEnv.snapshot``/``restore``).

Why: an explorer (Go-Explore, a tree search) that can return to a rare state does not pay the simulator steps
that led there again, and an exact return means that what it finds from there replays from the episode's start
to the bit. The snapshot holds the simulator's world, the system under test's own state (trackers, queues, its
random draws), the closed loop's last perception, the env's weather, step records and observation history.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from genesis_rl.sim.interface import ActorState, SensorFrame
from genesis_rl.sut.system.protocol import SystemOutput, SystemUnderTest
from genesis_rl.world.knobs import Weather
from genesis_rl.world.step_record import StepRecord


@dataclass(frozen=True)
class EnvSnapshot:
    """One step of one episode; restore it any number of times (every part is copied again on restore)."""

    scene_index: int
    episode_seed: int
    world_seed: int
    step: int  # ticks so far (== len(records))
    weather: Weather
    episode_start: Weather
    records: tuple[StepRecord, ...]  # frozen records: shared, not copied
    world: object  # the simulation's own snapshot (``Simulation.snapshot``)
    system: SystemUnderTest  # a state copy sharing the networks (``core.state_copy``)
    frame: SensorFrame
    ego: ActorState
    output: SystemOutput
    history: Any  # the observation's feature history (``FeatureHistory``)
    reward: Any  # the reward's own state (the falsification reward's worst danger so far)
    choosing_start: bool
    pending_bonus: float
