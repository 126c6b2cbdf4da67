"""A knob of the user's own, declared once: its range, its lite effect (a frame hook) and its sweep."""

from __future__ import annotations

import numpy as np

from genesis_rl.world.knobs import KnobSpec, register_knob


def dirty_lens(rgb: np.ndarray, depth: np.ndarray, value: float) -> np.ndarray:
    """Dirt on the lens: darkens the image toward its corners, up to 60 % at value 100."""
    h, w = rgb.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot((xx - w / 2) / (w / 2), (yy - h / 2) / (h / 2)) / np.sqrt(2)
    gain = 1.0 - 0.6 * (value / 100.0) * r
    return (rgb * gain[..., None]).astype(np.uint8)


LENS_DIRT = register_knob(KnobSpec("lens_dirt", 0.0, 100.0, "%", 0.0, description="dirt on the camera lens",
                                   lite="hook", frame_hook=dirty_lens, sweep=(0.0, 50.0, 100.0)))
