"""What the weather agent observes: the camera image (the paper's), and what a test engineer sees from outside.

The system under test is a black box except for what it reports, so the feature observation holds only:

- the knobs (the agent's own actions so far: the weather it made),
- the ego's speed (any test track measures it) and the time in the episode,
- the system's own outputs: its control (throttle, brake), how many vehicles it detects, the gap it
  perceives to the vehicle it follows (and whether it follows one), and its reported state (cruise,
  follow, red_light, emergency; the built-in controller's vocabulary, other states read as none).

With actor knobs among the knobs (``lead_decel``), also what a test engineer measures of the actor they drive,
as a target vehicle on a proving ground is measured: its true gap to the ego and the closing speed; with the
cut-in (``cut_in_ttc``), the same of the nearest vehicle ahead in a neighbouring lane, the one that would cut in.

Never the other vehicles' true states, the ground-truth boxes or the detector's loss: an agent that saw those
would find failures no tester could reproduce against a real black-box system. The last ``history`` feature
vectors are stacked (oldest first, zeros before the episode's first step), so a policy can see trends: the
lead's gap closing, detections dropping out as the fog rises.

With ``env.start_head``, one flag follows the stacked rows: 1 at the episode's first observation, whose action
chooses the start (the sun's altitude and bearing), 0 after it.

Modes (``env.observation``): ``image`` (the paper's), ``image+knobs`` (the image and the knob vector),
``features`` (the stacked features alone: a small MLP policy), ``image+features``.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from gymnasium import spaces

from genesis_rl.sim.interface import LeadInfo
from genesis_rl.sut.system.protocol import SystemOutput
from genesis_rl.world.knobs import KNOBS, Weather

OBSERVATIONS = ("image", "image+knobs", "features", "image+features")
#: the modes that carry the feature vector (and so the start step's flag, ``env.start_head``)
FEATURE_OBSERVATIONS = ("features", "image+features")
SPEED_SCALE = 30.0  # [m/s] speeds are divided by this (and clipped to [0, 1])
TIME_SCALE = 25.6  # [s] time is divided by this, the paper's episode (clipped): a campaign's --steps leaves it be
GAP_SCALE = 60.0  # [m] perceived gaps likewise (the built-in controller ignores detections farther away)
DETECTIONS_SCALE = 10.0
STATES = ("cruise", "follow", "red_light", "emergency")
#: the per-step features after the knobs, in order
FEATURES = ("ego_speed", "time", "n_detections", "follows", "perceived_gap", "throttle", "brake",
            *(f"state_{s}" for s in STATES))


#: appended when the knobs include an actor knob: the true gap to the vehicle ahead (the actor the tester
#: drives) and the closing speed, mapped from [-SPEED_SCALE, SPEED_SCALE] to [0, 1] (0.5: not closing)
ACTOR_FEATURES = ("actor_gap", "actor_closing_speed")
#: appended too when the knobs include ``cut_in_ttc``: the same two of the nearest vehicle ahead in a
#: neighbouring lane (the one a tester would have cut in)
NEIGHBOUR_FEATURES = ("neighbour_gap", "neighbour_closing_speed")


def has_actor_knobs(knobs: tuple[str, ...] | list[str]) -> bool:
    return any(KNOBS[k].is_actor for k in knobs if k in KNOBS)


def actor_feature_names(knobs: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The actor features a knob set adds (none for weather alone; the neighbour's with ``cut_in_ttc``)."""
    if not has_actor_knobs(knobs):
        return ()
    return ACTOR_FEATURES + (NEIGHBOUR_FEATURES if "cut_in_ttc" in knobs else ())


def feature_size(n_knobs: int, actors: bool | tuple[str, ...] = False) -> int:
    """``actors``: the actor features in use (``actor_feature_names``); True: :data:`ACTOR_FEATURES`."""
    extra = ACTOR_FEATURES if actors is True else (actors or ())
    return n_knobs + len(FEATURES) + len(extra)


def _gap_and_closing(other: LeadInfo | None, ego_speed: float) -> tuple[float, float]:
    gap, closing = (GAP_SCALE, 0.0) if other is None else (other.gap, ego_speed - other.speed)
    return min(max(gap / GAP_SCALE, 0.0), 1.0), min(max(0.5 + 0.5 * closing / SPEED_SCALE, 0.0), 1.0)


def step_features(weather: Weather, knobs: tuple[str, ...], ego_speed: float, time_s: float,
                  output: SystemOutput | None, lead: LeadInfo | None = None, actors: bool | tuple[str, ...] = False,
                  neighbour: LeadInfo | None = None) -> np.ndarray:
    """One step's features in [0, 1] (see the module doc); ``output`` None: the system has not answered;
    ``actors``: append :data:`ACTOR_FEATURES` from ``lead`` (None: nobody ahead, gap 1 and not closing), and
    :data:`NEIGHBOUR_FEATURES` from ``neighbour`` when ``actors`` names them."""
    out = np.zeros(feature_size(len(knobs), actors), np.float32)
    k = len(knobs)
    out[:k] = weather.normalized(knobs)
    out[k] = min(max(ego_speed / SPEED_SCALE, 0.0), 1.0)
    out[k + 1] = min(max(time_s / TIME_SCALE, 0.0), 1.0)
    if output is not None:
        out[k + 2] = min(len(output.detections) / DETECTIONS_SCALE, 1.0)
        gap = output.lead_distance
        if gap is not None and math.isfinite(gap):
            out[k + 3] = 1.0
            out[k + 4] = min(max(gap / GAP_SCALE, 0.0), 1.0)
        out[k + 5] = output.control.throttle
        out[k + 6] = output.control.brake
        if output.status in STATES:
            out[k + 7 + STATES.index(output.status)] = 1.0
    if actors:
        a = k + len(FEATURES)
        out[a], out[a + 1] = _gap_and_closing(lead, ego_speed)
        if isinstance(actors, tuple) and NEIGHBOUR_FEATURES[0] in actors:
            out[a + 2], out[a + 3] = _gap_and_closing(neighbour, ego_speed)
    return out


class FeatureHistory:
    """The last ``history`` feature vectors, oldest first, flattened; zeros before the first."""

    def __init__(self, n_knobs: int, history: int, actors: bool | tuple[str, ...] = False) -> None:
        self.size = feature_size(n_knobs, actors)
        self.history = int(history)
        self._rows: deque[np.ndarray] = deque(maxlen=self.history)
        self.reset()

    def reset(self) -> None:
        self._rows.clear()
        for _ in range(self.history):
            self._rows.append(np.zeros(self.size, np.float32))

    def push(self, row: np.ndarray) -> np.ndarray:
        self._rows.append(row.astype(np.float32, copy=False))
        return self.vector()

    def vector(self) -> np.ndarray:
        return np.concatenate(list(self._rows))


def observation_space(mode: str, obs_height: int, obs_width: int, n_knobs: int, history: int,
                      actors: bool | tuple[str, ...] = False, start_head: bool = False) -> spaces.Space:
    """``start_head``: one more feature after the stacked rows, 1 at the step that chooses the start."""
    image = spaces.Box(0, 255, (obs_height, obs_width, 3), np.uint8)
    features = spaces.Box(0.0, 1.0, (history * feature_size(n_knobs, actors) + int(start_head),), np.float32)
    if mode == "image":
        return image
    if mode == "image+knobs":
        return spaces.Dict({"image": image, "knobs": spaces.Box(0.0, 1.0, (n_knobs,), np.float32)})
    if mode == "features":
        return features
    return spaces.Dict({"image": image, "features": features})


def sb3_policy(mode: str) -> str:
    """The Stable-Baselines3 policy class name for an observation mode."""
    return {"image": "CnnPolicy", "features": "MlpPolicy"}.get(mode, "MultiInputPolicy")
