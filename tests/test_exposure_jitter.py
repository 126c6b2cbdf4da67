"""The camera's exposure jitter: a frame-to-frame gain drawn from the world seed, off unless asked for."""

from __future__ import annotations

import numpy as np
import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv


@pytest.fixture(scope="module")
def envs():
    """One env with the jitter and one without, on the same two highway scenes."""
    made = {j: GenesisEnv(EnvConfig(map="highway", scenes=2, episode_steps=24, camera_width=96, camera_height=72,
                                    camera_exposure_jitter=j)) for j in (0.0, 0.1)}
    yield made
    for env in made.values():
        env.close()


def _frames(env: GenesisEnv, world_seed: int, steps: int = 24) -> list[np.ndarray]:
    env.reset(options={"scene": 1, "episode_seed": 5, "world_seed": world_seed})
    out = []
    for _ in range(steps):
        env.step(np.zeros(env.mapper.action_dim, np.float32))
        out.append(env.camera_frame().astype(np.float64))
    return out


def test_the_jitter_is_drawn_from_the_world_seed_and_varies_the_frames_brightness(envs):
    plain = _frames(envs[0.0], 11)
    jittered = _frames(envs[0.1], 11)
    assert [f.tobytes() for f in jittered] == [f.tobytes() for f in _frames(envs[0.1], 11)]  # the same world
    assert [f.tobytes() for f in jittered] != [f.tobytes() for f in _frames(envs[0.1], 12)]  # other gains
    ratio = np.log([j.mean() / p.mean() for j, p in zip(jittered, plain, strict=True)])
    # a log-sd of 0.1 on the gain before the tone curve: the frames' mean brightness moves by several percent
    # from frame to frame, in both directions (the curve and the 8-bit cast compress it somewhat)
    assert 0.03 < float(np.std(ratio)) < 0.15 and ratio.min() < 0.0 < ratio.max()


def test_without_jitter_the_camera_draws_nothing_more(envs):
    a, b = _frames(envs[0.0], 11, steps=6), _frames(envs[0.0], 12, steps=6)
    assert [f.tobytes() for f in a] != [f.tobytes() for f in b]  # the sensor noise follows the world seed
    assert max(abs(x.mean() - y.mean()) for x, y in zip(a, b, strict=True)) < 0.5  # but no gain changes


def test_a_jitter_out_of_range_or_on_carla_is_refused_naming_the_field():
    with pytest.raises(UserInputError, match=r"env\.camera_exposure_jitter"):
        EnvConfig(camera_exposure_jitter=0.8)
    with pytest.raises(UserInputError, match=r"camera_exposure_jitter = 0.05 is lite's camera model.*carla"):
        EnvConfig(camera_exposure_jitter=0.05, backend="carla")
