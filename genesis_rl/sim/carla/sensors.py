"""Camera images from CARLA's raw buffers, and frame-matched delivery in synchronous mode.

Sensor callbacks run on the client's worker threads and may deliver after ``world.tick()`` returns; each
sensor puts its data in a queue and the simulation takes, for every tick, the item whose ``frame`` matches
the tick's frame (older ones are dropped), so an observation is never a frame late.
"""

from __future__ import annotations

import queue
from typing import Any

import numpy as np

#: CARLA's depth camera: 24-bit fixed point over 0..1000 m, R least significant
DEPTH_FAR = 1000.0
_DEPTH_SCALE = DEPTH_FAR / (256.0**3 - 1.0)


def bgra_to_rgb(raw: bytes | memoryview, width: int, height: int) -> np.ndarray:
    """``carla.Image.raw_data`` (BGRA, 8 bit) -> RGB (H, W, 3) uint8."""
    bgra = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 4)
    return np.ascontiguousarray(bgra[:, :, 2::-1])


def decode_depth(raw: bytes | memoryview, width: int, height: int) -> np.ndarray:
    """Raw ``sensor.camera.depth`` data -> depth along the optical axis in metres, (H, W) float32:
    (R + 256 G + 256^2 B) / (256^3 - 1) * 1000."""
    bgra = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 4).astype(np.float64)
    code = bgra[:, :, 2] + 256.0 * bgra[:, :, 1] + 65536.0 * bgra[:, :, 0]
    return (code * _DEPTH_SCALE).astype(np.float32)


def encode_depth(depth: np.ndarray) -> bytes:
    """The inverse of :func:`decode_depth` (BGRA bytes), for tests and synthetic frames."""
    code = np.clip(np.rint(np.asarray(depth, dtype=np.float64) / _DEPTH_SCALE), 0, 256**3 - 1).astype(np.uint32)
    bgra = np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255, np.full_like(code, 255)], axis=-1)
    return bgra.astype(np.uint8).tobytes()


class FrameQueue:
    """Holds one sensor's measurements until the simulation asks for a frame."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._q: queue.Queue[Any] = queue.Queue()

    def put(self, data: Any) -> None:
        self._q.put(data)

    def get(self, frame: int, timeout: float) -> Any:
        """The measurement of ``frame``; raises TimeoutError when it does not come within ``timeout`` s."""
        while True:
            try:
                data = self._q.get(timeout=timeout)
            except queue.Empty:
                raise TimeoutError(f"no {self.name} data for frame {frame} within {timeout:g} s") from None
            if data.frame >= frame:
                return data
