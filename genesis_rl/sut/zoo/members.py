"""The zoo: systems under test whose in-ODD weaknesses are known before any adversary runs.

An adversary can only be judged against ground truth: a *weakness* member fails inside its ODD in a stated
trigger region, a *control* has no in-ODD weakness, so whatever an adversary reports on it is a false alarm
candidate. Each member names its system as ``EnvConfig.system`` does, the ODD it is released for (shipped
under ``genesis_rl/sut/zoo/odd/``), its map and the env settings it is tested under. Pages: docs/zoo.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.zoo.trigger import EMPTY, Bound, TriggerRegion
from genesis_rl.world.scenes.placement import TRAFFIC

KINDS = ("weakness", "control")
MAPS = ("urban", "highway")
#: the shipped ODD files
ODD_DIR = Path(__file__).parent / "odd"
#: the shipped weights of the members' own detectors (each reproduced by the command on its page, docs/zoo.md)
WEIGHTS_DIR = Path(__file__).parent / "weights"
#: env keys a member sets through its own fields, never through ``env``
_OWN_KEYS = frozenset({"map", "system", "system_kwargs", "odd", "catalog"})


@dataclass(frozen=True)
class ZooMember:
    """One system under test inside one ODD, with its weakness stated as a trigger region (empty: a control)."""

    name: str
    kind: str
    summary: str
    system: str  # as ``system.protocol.load_system`` takes it: builtin, oracle, package.module:Class
    odd: str  # file name under ODD_DIR
    map: str
    trigger: TriggerRegion
    system_kwargs: Mapping[str, Any] = field(default_factory=dict)
    env: Mapping[str, Any] = field(default_factory=dict)  # other EnvConfig fields (dynamics, knobs, ...)
    traffic: str = "mixed"  # the generated scenes' traffic (CampaignSpec.traffic): mixed or free_flow

    def __post_init__(self) -> None:
        where = f"zoo member '{self.name}'"
        if self.kind not in KINDS:
            raise UserInputError(f"{where}: kind = '{self.kind}'; allowed: {', '.join(KINDS)}")
        if self.map not in MAPS:
            raise UserInputError(f"{where}: map = '{self.map}'; allowed: {', '.join(MAPS)}")
        if (self.kind == "control") != self.trigger.empty:  # a control has nothing to find; a weakness something
            raise UserInputError(f"{where}: a {self.kind}'s trigger region must be "
                                 f"{'empty' if self.kind == 'control' else 'non-empty'}")
        if self.traffic not in TRAFFIC:
            raise UserInputError(f"{where}: traffic = '{self.traffic}'; allowed: {', '.join(TRAFFIC)}")
        own = sorted(set(self.env) & _OWN_KEYS)  # other keys are checked where EnvConfig is built
        if own:
            raise UserInputError(f"{where}: env key(s) {own} are the member's own fields; set them there")

    @property
    def odd_path(self) -> Path:
        return ODD_DIR / self.odd


def env_settings(member: ZooMember) -> dict[str, Any]:
    """The ``EnvConfig`` fields a campaign on ``member`` plays under (``CampaignSpec.env``); a fresh dict. A
    campaign sets ``episode_steps`` from its own ``steps`` (and the catalog's map): pass the member's there."""
    return {"map": member.map, "system": member.system, "system_kwargs": dict(member.system_kwargs),
            "odd": str(member.odd_path), **member.env}


_LOW_SUN = ZooMember(
    name="low_sun", kind="weakness", system="builtin", odd="urban_day.toml", map="urban",
    summary=("The built-in system (its CNN vehicle detector behind the IDM following controller) in city "
             "traffic by day. Its detector's training data drew the sun's altitude from 15 to 90 deg only "
             "(perception/dataset.py, _typical), so a sun lower than 15 deg is a condition it never saw; the "
             "day ODD (urban_day) allows it, glare included. The region touches the ODD's altitude bound (0 deg), "
             "so a constant schedule reaches it: a corner weakness, not an interior band."),
    trigger=TriggerRegion((Bound("sun_altitude_angle", 0.0, 15.0),)),
    env={"dynamics": "natural", "episode_steps": 256},
)

_LOW_SUN_HIGHWAY = ZooMember(
    name="low_sun_highway", kind="weakness", system="builtin", odd="highway_day.toml", map="highway",
    summary=("The built-in system inside highway_day on the highway: by day with no low sun in the camera. Its "
             "detector never saw a sun under 15 deg (as low_sun), and highway_day allows one as long as it is not "
             "in the camera's view. Found by the benchmark itself: with natural starts (0.15.0) adversaries found "
             "4 perception failures with the sun 0.06-1.6 deg up where builtin_highway, its earlier name, was "
             "listed as a control (docs/results/14-benchmark-log.md, first measurement). A corner weakness on the "
             "highway."),
    trigger=TriggerRegion((Bound("sun_altitude_angle", 0.0, 15.0),)),
    env={"dynamics": "natural"},
)

#: the glare-blind detector: `genesis-rl detector train --condition sun_behind --frames 2400 --epochs 12`
GLARE_BLIND_WEIGHTS = WEIGHTS_DIR / "glare_blind_detector.pt"

_GLARE_BLIND = ZooMember(
    name="glare_blind", kind="weakness", system="builtin", system_kwargs={"weights": str(GLARE_BLIND_WEIGHTS)},
    odd="urban_any_hour.toml", map="urban",
    summary=("The built-in detector architecture trained on data from every hour (night, dusk, day) from which "
             "every frame with the sun in the picture was dropped as unlabellable (perception/dataset.py, "
             "_sun_behind: never within 60 deg of the camera's heading), behind the IDM following controller, in "
             "city traffic at any hour (urban_any_hour, glare allowed). It knows night, dusk and a low sun's dim "
             "light from behind; a low sun ahead washes the cars out. An interior weakness: a band of sun "
             "altitude (below 15 deg) at headings toward the sun, between night and noon, which neither corner "
             "of the sun's altitude reaches."),
    trigger=TriggerRegion((Bound.flag("sun_glare"), Bound("sun_altitude_angle", 0.0, 15.0))),
    env=dict(_LOW_SUN.env),  # the urban weather member's: natural dynamics, 256 steps
)

_BUILTIN_HIGHWAY = ZooMember(
    name="builtin_highway", kind="control", system="builtin", odd="highway_high_sun.toml", map="highway",
    summary=("The built-in system on the highway inside highway_high_sun: highway_day with the sun at least 15 "
             "deg up, the light its detector's data held. No adversary found a weather failure of it there under "
             "natural dynamics in 50 scenes that started at noon (docs/results/06-natural-edge-cases.md and "
             "07-reactive-adversary-in-odd.md). Its one in-ODD "
             "collision there (scene 39) is weather-independent: sunny has it too and the oracle replay crashes "
             "as well. A control: every in-ODD failure an adversary reports on it is a false alarm candidate."),
    trigger=EMPTY,
    env={"dynamics": "natural"},
)

_ORACLE_HIGHWAY = ZooMember(
    name="oracle_highway", kind="control", system="oracle", odd="highway_day.toml", map="highway",
    summary=("The same controller on ground-truth boxes (the oracle: perfect perception) inside highway_day on "
             "the highway. Weather cannot blind it, so a weather adversary has nothing to find."),
    trigger=EMPTY,
    env={"dynamics": "natural"},
)

#: the highway profile of our controller: the main line's 25 m/s and a 120 m perception range, where the
#: built-in profile (13.9 m/s, 60 m) is BehaviorAgent's urban one; the time gap stays 1.5 s (a common ACC
#: setting; at ACC's shortest, 1.0 s, a careful driver cannot avoid a lead braking at 6 m/s^2 either)
HIGHWAY_PROFILE: Mapping[str, float] = {"max_speed": 25.0, "perception_range": 120.0}
#: the timing members' knobs: the paper's weather knobs and the lead's braking demand, one action space
_WEATHER_AND_BRAKING = ("fog_density", "precipitation", "precipitation_deposits", "sun_altitude_angle",
                        "sun_azimuth_angle", "lead_decel")
#: the env of the timing members (both pairs): natural rates, weather and braking, 256-step episodes
_TIMING_ENV: Mapping[str, Any] = {"dynamics": "natural", "knobs": _WEATHER_AND_BRAKING, "episode_steps": 256}
#: the latency of latency_braking's perception pipeline [s]
PIPELINE_LATENCY_S = 1.5

_LATENCY_BRAKING = ZooMember(
    name="latency_braking", kind="weakness", system="latency",
    system_kwargs={"latency_s": PIPELINE_LATENCY_S, "controller": dict(HIGHWAY_PROFILE)},
    odd="highway_braking.toml", map="highway", traffic="free_flow",
    summary=("The built-in detector and controller at the highway profile (25 m/s, 120 m range, 1.5 s time gap) "
             f"behind a perception pipeline whose detections reach the controller {PIPELINE_LATENCY_S:g} s late, "
             "in free-flowing motorway traffic by day (highway_braking: the sun >= 15 deg up, a lead braking up to "
             "6 m/s^2). In steady following the time gap absorbs the delay; when the lead brakes hard, the "
             "controller acts on where it was 1.5 s before and brakes too late. A timing weakness: the trigger is "
             "an actor's event, not a weather corner."),
    trigger=TriggerRegion((Bound("lead_decel", 4.0, 8.0),)),
    env=dict(_TIMING_ENV),
)

_BUILTIN_BRAKING = ZooMember(
    name="builtin_braking", kind="control", system="builtin", system_kwargs={"controller": dict(HIGHWAY_PROFILE)},
    odd="highway_braking.toml", map="highway", traffic="free_flow",
    summary=("latency_braking's system without the latency: the built-in system at the highway profile in the same "
             "free-flowing traffic and domain. It brakes in time for a lead braking at the domain's 6 m/s^2, so an "
             "adversary turning the weather and the lead's braking has nothing to find: the timing control."),
    trigger=EMPTY,
    env=dict(_TIMING_ENV),
)

#: how long fog_braking's visibility estimate takes to follow the fog (its planted weakness) and the control's [s]
SLOW_VISIBILITY_S, QUICK_VISIBILITY_S = 12.0, 0.5
#: where the fog-braking pair's episodes start: mist at about 150 m of visibility, inside highway_fog_braking
FOG_BRAKING_START = "fog_density=26"

_FOG_BRAKING = ZooMember(
    name="fog_braking", kind="weakness", system="adaptive",
    system_kwargs={"smoothing_s": SLOW_VISIBILITY_S, "controller": dict(HIGHWAY_PROFILE)},
    odd="highway_fog_braking.toml", map="highway", traffic="free_flow",
    summary=("A competent controller: the built-in detector at the highway profile behind a controller that "
             "estimates the visibility from its camera and slows so that it can stop within the distance its "
             "detector sees, in free-flowing motorway traffic by day, in fog down to 50 m (highway_fog_braking). "
             "Constant fog makes it careful. Its estimate follows the fog over "
             f"{SLOW_VISIBILITY_S:g} s, so when the fog thickens and the lead brakes a second or more later, it is "
             "still too fast for what it can see. A timing weakness: on the scenes probed, fog and braking together, "
             "or either alone, found nothing, and braking a second or two after the fog began failed 5 of 8; a "
             "constant schedule still triggers it at the domain's 50 m floor on some scenes (docs/zoo.md)."),
    trigger=TriggerRegion((Bound("lead_decel", 4.0, 8.0), Bound("visibility_m", 50.0, 100.0))),
    env={**_TIMING_ENV, "start_weather": FOG_BRAKING_START},
)

_ADAPTIVE_BRAKING = ZooMember(
    name="adaptive_braking", kind="control", system="adaptive",
    system_kwargs={"smoothing_s": QUICK_VISIBILITY_S, "controller": dict(HIGHWAY_PROFILE)},
    odd="highway_fog_braking.toml", map="highway", traffic="free_flow",
    summary=(f"fog_braking's system with an estimate that follows the fog within {QUICK_VISIBILITY_S:g} s: it slows "
             "as the fog thickens, so a lead braking at 6 m/s^2 in the thickening fog appears in time; the control "
             "of the fog-braking timing pair."),
    trigger=EMPTY,
    env={**_TIMING_ENV, "start_weather": FOG_BRAKING_START},
)

_HIGHWAY_SPEED_FOG = ZooMember(
    name="highway_speed_fog", kind="weakness", system="builtin", system_kwargs={"controller": dict(HIGHWAY_PROFILE)},
    odd="highway_fog_braking.toml", map="highway", traffic="free_flow",
    summary=("The highway profile: the built-in system at the main line's 25 m/s with a 120 m perception range and "
             "a 1.5 s time gap, released (as fog_braking's adaptive system is) into fog down to 50 m. Its speed does "
             "not follow what it sees: at 25 m/s it needs about 75 m to stop, while its detector finds a car at a "
             "third to a half of the fog's visibility. Fog alone is harmless in free-flowing traffic (the lead pulls "
             "away unseen); a lead braking hard in thick fog is met too late. A corner weakness of an actor event "
             "and a weather condition together: the stopping distance against the ODD's visibility bound."),
    trigger=TriggerRegion((Bound("lead_decel", 4.0, 8.0), Bound("visibility_m", 50.0, 100.0))),
    env={**_TIMING_ENV, "start_weather": FOG_BRAKING_START},
)

#: stall_braking's camera: a stutter of STALL_WARNING_S, then a stall of STALL_S, starting once an episode
#: uniformly in [STALL_EARLIEST_S, STALL_LATEST_S) of its 700 steps (35 s), so that the stall ends inside it [s]
STALL_S, STALL_WARNING_S, STALL_EARLIEST_S, STALL_LATEST_S = 2.5, 4.0, 4.0, 28.0
_STALL_STEPS = 700

_STALL_BRAKING = ZooMember(
    name="stall_braking", kind="weakness", system="stall",
    system_kwargs={"stall_s": STALL_S, "warning_s": STALL_WARNING_S, "earliest_s": STALL_EARLIEST_S,
                   "latest_s": STALL_LATEST_S, "controller": dict(HIGHWAY_PROFILE)},
    odd="highway_braking.toml", map="highway", traffic="free_flow",
    summary=("A reactive weakness: the built-in system at the highway profile behind a camera whose stream, once an "
             f"episode at a moment the world's seed draws, stutters for {STALL_WARNING_S:g} s (every other frame "
             f"a repeat) and then stalls for {STALL_S:g} s (the last frame re-delivered), in free-flowing motorway "
             "traffic by day (highway_braking). The controller tracks the frozen picture as if the gap held: a lead "
             "braking hard from the stutter on is slow and close by the stall and is met too late; braking long "
             "before or after is met in time. Only an adversary that watches the system (its detections repeat in "
             "the stutter) can time the braking: the moment differs every episode (sut/system/stall.py)."),
    trigger=TriggerRegion((Bound("lead_decel", 4.0, 8.0), Bound.flag("stale_frames"))),
    env={**_TIMING_ENV, "episode_steps": _STALL_STEPS},
)

#: the real-photo member's episodes: a COCO frame costs ~4x the built-in detector's, so half the usual length
_COCO_STEPS = 256

_COCO_LOW_SUN = ZooMember(
    name="coco_low_sun", kind="weakness", system="coco", odd="highway_day.toml", map="highway",
    summary=("The paper's kind of system: darknet's yolov3-tiny trained on COCO photographs (cars, buses, trucks) "
             "behind our localisation and IDM following controller, on the highway inside highway_day (the sun may "
             "stand low as long as it is not in the camera). In clear noon it drives the highway's mixed traffic "
             "safely (48 of 50 scenes, docs/realism.md); a low sun's long shadows and warm, dim light cost it the "
             "cars ahead, as they cost it 4 of 6 urban scenes at 5 deg. A corner weakness of a detector trained "
             "on photographs, in the conditions the photographs rarely held."),
    trigger=TriggerRegion((Bound("sun_altitude_angle", 0.0, 15.0),)),
    env={"dynamics": "natural", "episode_steps": _COCO_STEPS},
)

#: every member by name
ZOO: dict[str, ZooMember] = {m.name: m for m in (_LOW_SUN, _LOW_SUN_HIGHWAY, _LATENCY_BRAKING, _FOG_BRAKING,
                                                 _HIGHWAY_SPEED_FOG, _COCO_LOW_SUN, _GLARE_BLIND, _STALL_BRAKING,
                                                 _BUILTIN_HIGHWAY,
                                                 _ORACLE_HIGHWAY, _BUILTIN_BRAKING, _ADAPTIVE_BRAKING)}


def zoo_member(name: str) -> ZooMember:
    """The member called ``name``; an unknown name is refused, naming the members."""
    if name not in ZOO:
        raise UserInputError(f"zoo member '{name}' is unknown; allowed: {', '.join(ZOO)}")
    return ZOO[name]
