"""Simulator interface: a backend is a connection (lives long), a simulation is one episode.

After Scenic's ``Simulator``/``Simulation`` split: a :class:`Backend` creates :class:`Simulation` objects;
a simulation loads one scene, takes knob settings and the ego's control, advances by a fixed time step
(CARLA's synchronous mode, 0.05 s) and returns sensor frames. It is destroyed in ``finally`` (use it as a
context manager), so a crash never leaves actors behind on a server.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from genesis_rl.core.errors import UserInputError
from genesis_rl.world.knobs import Weather
from genesis_rl.world.scenes.catalog import Scene
from genesis_rl.world.step_record import RecordedBox

#: Simulation time step in seconds (CARLA synchronous mode with fixed_delta_seconds = 0.05).
FIXED_DELTA_SECONDS = 0.05


@dataclass(frozen=True)
class VehicleControl:
    """Ego control, as CARLA's ``VehicleControl``: throttle and brake in [0, 1], steer in [-1, 1]
    (positive steers right, as in CARLA)."""

    throttle: float = 0.0
    brake: float = 0.0
    steer: float = 0.0

    def __post_init__(self) -> None:
        for name, lo, hi in (("throttle", 0.0, 1.0), ("brake", 0.0, 1.0), ("steer", -1.0, 1.0)):
            v = getattr(self, name)
            if not (math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"VehicleControl.{name} = {v} must be in [{lo}, {hi}]")


#: the largest exposure jitter a camera takes (a log-sd of 0.5 is a gain off by 65 % one frame in three)
EXPOSURE_JITTER_MAX = 0.5


@dataclass(frozen=True)
class CameraConfig:
    """The ego's RGB + depth camera. Mount is in the ego frame (x forward, y left, z up, metres, from the
    vehicle's centre on the ground); fov is horizontal, as CARLA's ``fov`` attribute."""

    width: int = 320
    height: int = 240
    fov_deg: float = 90.0
    mount_x: float = 0.8
    mount_y: float = 0.0
    mount_z: float = 1.5
    pitch_deg: float = 0.0
    max_range: float = 200.0
    #: frame-to-frame exposure jitter of an auto-exposure camera: the standard deviation of the log of each
    #: frame's exposure gain, drawn from the world seed (0: none, as every preset; ``EXPOSURE_JITTER_MAX`` at most)
    exposure_jitter: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.exposure_jitter <= EXPOSURE_JITTER_MAX:
            raise ValueError(f"camera exposure_jitter must be in 0..{EXPOSURE_JITTER_MAX}, got {self.exposure_jitter}")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ValueError(f"camera width/height must be in 16..4096, got {self.width}x{self.height}")
        if not 10.0 <= self.fov_deg <= 170.0:
            raise ValueError(f"camera fov_deg must be in 10..170, got {self.fov_deg}")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (same for both axes: square pixels)."""
        return self.width / (2.0 * math.tan(math.radians(self.fov_deg) / 2.0))

    def intrinsics(self) -> np.ndarray:
        """3x3 pinhole matrix K (pixel centres at +0.5)."""
        f = self.focal_px
        return np.array([[f, 0.0, self.width / 2.0], [0.0, f, self.height / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class GroundTruthBox:
    """A visible vehicle in the image: pixel box [x0, x1) x [y0, y1) clipped at the border, from its visible
    pixels (occlusion-aware). ``distance`` is the metric depth (along the optical axis) of its nearest
    visible point; ``visible_fraction`` the share of its projected box not hidden by others."""

    vehicle_id: int
    x0: int
    y0: int
    x1: int
    y1: int
    distance: float
    visible_fraction: float
    truncated: bool

    @property
    def xyxy(self) -> tuple[int, int, int, int]:
        return (self.x0, self.y0, self.x1, self.y1)

    @property
    def area(self) -> int:
        return max(0, self.x1 - self.x0) * max(0, self.y1 - self.y0)

    def recorded(self) -> RecordedBox:
        """The box as step records and files keep it (distance and visible fraction to 3 decimals)."""
        return RecordedBox(self.vehicle_id, (self.x0, self.y0, self.x1, self.y1), round(self.distance, 3),
                           round(self.visible_fraction, 3), self.truncated)

    def as_dict(self) -> dict[str, Any]:
        return self.recorded().to_row()


@dataclass
class SensorFrame:
    """One camera frame: RGB (H, W, 3) uint8, metric depth (H, W) float32 in metres along the optical
    axis (as CARLA's depth camera), per-pixel labels (H, W) uint8 (see ``lite.render.labels``) and the
    ground-truth boxes of visible vehicles."""

    step: int
    rgb: np.ndarray
    depth: np.ndarray
    boxes: list[GroundTruthBox]
    labels: np.ndarray | None = None


@dataclass(frozen=True)
class ActorState:
    """Ground truth of one vehicle (world frame: x east, y north, z up; yaw counter-clockwise from x)."""

    vehicle_id: int
    role: str
    make: str
    x: float
    y: float
    z: float
    yaw: float
    pitch: float
    speed: float
    length: float
    width: float
    height: float


@dataclass(frozen=True)
class Collision:
    """Two vehicles' boxes overlapped at ``step``; speeds (m/s) are those just before the impact."""

    step: int
    vehicle_a: int
    vehicle_b: int
    speed_a: float
    speed_b: float
    relative_speed: float


@dataclass(frozen=True)
class LeadInfo:
    """The nearest vehicle ahead in the ego's path (ground truth): bumper-to-bumper gap in metres."""

    vehicle_id: int
    gap: float
    speed: float


class SnapshotUnsupported(UserInputError):
    """The backend cannot save and restore a running simulation (``Simulation.snapshot``)."""


@dataclass(frozen=True)
class TickResult:
    step: int
    time: float
    collisions: list[Collision] = field(default_factory=list)


class Simulation(abc.ABC):
    """One episode on a backend. Subclasses implement the abstract methods; use as a context manager.

    Subclasses set ``_step`` (ticks so far, 0 at creation) and ``_weather`` (the knobs the next frame
    uses) in ``__init__`` and advance ``_step`` in ``tick``; the accessors below read them."""

    dt: float = FIXED_DELTA_SECONDS
    _step: int
    _weather: Weather

    def __enter__(self) -> Simulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.destroy()

    @property
    def step_count(self) -> int:
        return self._step

    @property
    def weather(self) -> Weather:
        return self._weather

    def set_weather(self, weather: Weather) -> None:
        """Set every knob; takes effect for the next frame."""
        self._weather = weather

    @abc.abstractmethod
    def apply_ego_control(self, control: VehicleControl) -> None:
        """Control the ego uses from the next tick on (held until changed)."""

    @abc.abstractmethod
    def tick(self) -> TickResult:
        """Advance the world by ``dt``."""

    @abc.abstractmethod
    def observe(self) -> SensorFrame:
        """Render the ego camera at the current state."""

    @abc.abstractmethod
    def actors(self) -> list[ActorState]:
        """Ground-truth state of every vehicle, the ego first."""

    @abc.abstractmethod
    def lead(self) -> LeadInfo | None:
        """The vehicle ahead in the ego's path, or None when the path is clear within range."""

    @abc.abstractmethod
    def destroy(self) -> None:
        """Release everything this episode created. Safe to call twice."""

    def ego(self) -> ActorState:
        return self.actors()[0]

    def neighbour_ahead(self) -> LeadInfo | None:
        """The nearest vehicle ahead of the ego in a neighbouring lane of the same direction (the one a cut-in
        would bring in front of it), or None; none by default (a backend without lanes to ask)."""
        return None

    def actor_events(self) -> list[ActorEvent]:
        """The events the actor knobs caused so far in this episode (cut-ins, a lead braking), oldest first;
        none by default (a backend that realises no actor knob)."""
        return []

    #: why this backend cannot snapshot a simulation (shown to whoever asks for one); None: it can
    snapshot_unsupported: ClassVar[str | None] = (
        "this backend does not save and restore simulations; use an adversary that replays episodes from their "
        "start (cmaes, cem, random_search, mcts)")

    def snapshot(self) -> object:
        """The whole state of this episode's world (traffic, ego, time, weather, random streams), such that
        ``restore`` and the same controls and weather give the same ticks and frames as the uninterrupted run,
        to the bit. What the system under test holds is snapshotted by its owner (``GenesisEnv.snapshot``)."""
        raise SnapshotUnsupported(f"snapshots: {self.snapshot_unsupported}")

    def restore(self, state: object) -> None:
        """Put the world back where ``snapshot`` found it; the state may be restored any number of times."""
        raise SnapshotUnsupported(f"snapshots: {self.snapshot_unsupported}")

    def context_extras(self) -> dict[str, Any]:
        """What this backend adds to the system's :class:`~genesis_rl.sut.system.protocol.EpisodeContext`
        ``extras`` (e.g. CARLA's traffic-light states); nothing by default."""
        return {}


@dataclass(frozen=True)
class ActorEvent:
    """An event an actor knob caused, as the careful-driver reference needs it: what happened, to
    which vehicle (scene index), when it began [s of episode time] and when a careful driver could first
    perceive it [s] (a cut-in: when the cutter has wandered ``CUT_IN_WANDER_M`` toward the ego's lane; a
    braking lead: the onset, its brake lights come on at once; None: not yet perceivable). ``ttc_s``,
    ``gap_m`` and ``closing_m_s``: the gap the cut-in was made into, at its onset (NaN for braking).
    ``perceived_ttc_s``: a cut-in's time-to-collision when it became perceivable, R157's measure (NaN until
    then, for braking, and in records written before 0.25; a cut-in's row always has the key, null when
    unknown)."""

    kind: str  # "cut_in" or "lead_braking"
    vehicle_id: int
    onset_s: float
    perceivable_s: float | None
    ttc_s: float = math.nan
    gap_m: float = math.nan
    closing_m_s: float = math.nan
    perceived_ttc_s: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "vehicle_id": self.vehicle_id, "onset_s": round(self.onset_s, 4),
                "perceivable_s": None if self.perceivable_s is None else round(self.perceivable_s, 4),
                **{k: (None if not math.isfinite(v) else round(v, 4))
                   for k, v in (("ttc_s", self.ttc_s), ("gap_m", self.gap_m), ("closing_m_s", self.closing_m_s))},
                # every cut-in says it was measured where R157 measures (null: never perceivable, or not closing)
                **({"perceived_ttc_s": round(self.perceived_ttc_s, 4) if math.isfinite(self.perceived_ttc_s) else None}
                   if self.kind == "cut_in" else {})}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ActorEvent:
        def num(key: str) -> float:
            v = d.get(key)
            return math.nan if v is None else float(v)

        p = d.get("perceivable_s")
        return cls(str(d["kind"]), int(d["vehicle_id"]), float(d["onset_s"]), None if p is None else float(p),
                   num("ttc_s"), num("gap_m"), num("closing_m_s"), num("perceived_ttc_s"))


@dataclass(frozen=True)
class ConnectionSettings:
    """Where a backend that talks to a simulator server finds it (``--carla-host`` ... or ``env.carla_*``);
    an embedded backend ignores them."""

    host: str = "localhost"
    port: int = 2000  # RPC port
    tm_port: int | None = None  # traffic manager port; None: the server's port + 6000 (one per run)
    timeout: float = 10.0  # [s] per client call


class Backend(abc.ABC):
    """A simulator connection: knows its maps, creates simulations, lives across episodes.

    A backend is named in ``genesis_rl.sim.backends.BACKENDS`` (built in) or by its import path
    ``package.module:Class``; the class attributes below are what the rest of the framework asks of it."""

    name: str = "abstract"
    #: the scene catalogs it drives: their ``backend`` field, a built-in backend's name ("lite", "carla");
    #: that backend's scene module generates and checks them. A subclass of LiteBackend drives lite catalogs.
    catalog_kind: ClassVar[str] = ""
    #: True when scenes cannot be generated on the fly: every command then needs a catalog file
    needs_catalog: ClassVar[bool] = False
    #: the actor knobs (``knobs.KnobSpec.is_actor``) its simulations realise; the env refuses the others
    actor_knobs: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_settings(cls, settings: ConnectionSettings) -> Backend:
        """A connected backend; an embedded one takes no settings."""
        return cls()

    @abc.abstractmethod
    def map_names(self) -> list[str]: ...

    @abc.abstractmethod
    def create_simulation(
        self,
        scene: Scene,
        *,
        seed: int,
        weather: Weather | None = None,
        camera: CameraConfig | None = None,
        render: bool = True,
    ) -> Simulation:
        """Load ``scene``; ``seed`` drives everything random in the episode (NPC behaviour, sensor noise)."""

    def close(self) -> None:
        """Release the connection (renderer, sockets)."""

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
