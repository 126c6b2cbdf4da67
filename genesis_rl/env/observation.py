"""What the weather agent observes: the camera image (the paper's), and what a test engineer sees from outside.

The system under test is a black box except for what it reports, so the feature observation holds only:

- the knobs (the agent's own actions so far: the weather it made),
- the ego's speed (any test track measures it) and the time in the episode,
- the system's own outputs: its control (throttle, brake), how many vehicles it detects, the gap it
  perceives to the vehicle it follows (and whether it follows one), and its reported state (cruise,
  follow, red_light, emergency; the built-in controller's vocabulary, other states read as none).

Never the other vehicles' true states, the ground-truth boxes or the detector's loss: an agent that saw those
would find failures no tester could reproduce against a real black-box system. The last ``history`` feature
vectors are stacked (oldest first, zeros before the episode's first step), so a policy can see trends: the
lead's gap closing, detections dropping out as the fog rises.

Modes (``env.observation``): ``image`` (the paper's), ``image+knobs`` (the image and the knob vector),
``features`` (the stacked features alone: a small MLP policy), ``image+features``.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from gymnasium import spaces

from genesis_rl.knobs import Weather
from genesis_rl.system.protocol import SystemOutput

OBSERVATIONS = ("image", "image+knobs", "features", "image+features")
SPEED_SCALE = 30.0  # [m/s] speeds are divided by this (and clipped to [0, 1])
TIME_SCALE = 25.6  # [s] time is divided by this, the paper's episode (clipped): a campaign's --steps leaves it be
GAP_SCALE = 60.0  # [m] perceived gaps likewise (the built-in controller ignores detections farther away)
DETECTIONS_SCALE = 10.0
STATES = ("cruise", "follow", "red_light", "emergency")
#: the per-step features after the knobs, in order
FEATURES = ("ego_speed", "time", "n_detections", "follows", "perceived_gap", "throttle", "brake",
            *(f"state_{s}" for s in STATES))


def feature_size(n_knobs: int) -> int:
    return n_knobs + len(FEATURES)


def step_features(weather: Weather, knobs: tuple[str, ...], ego_speed: float, time_s: float,
                  output: SystemOutput | None) -> np.ndarray:
    """One step's features in [0, 1] (see the module doc); ``output`` None: the system has not answered."""
    out = np.zeros(feature_size(len(knobs)), np.float32)
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
    return out


class FeatureHistory:
    """The last ``history`` feature vectors, oldest first, flattened; zeros before the first."""

    def __init__(self, n_knobs: int, history: int) -> None:
        self.size = feature_size(n_knobs)
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


def observation_space(mode: str, obs_height: int, obs_width: int, n_knobs: int, history: int) -> spaces.Space:
    image = spaces.Box(0, 255, (obs_height, obs_width, 3), np.uint8)
    features = spaces.Box(0.0, 1.0, (history * feature_size(n_knobs),), np.float32)
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
