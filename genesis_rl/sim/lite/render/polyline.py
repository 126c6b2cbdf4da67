"""Which vertices of densely sampled road polylines the renderer needs (Douglas-Peucker on several lines).

The maps sample road centrelines every 0.5 m, which the lane graph wants for lane keeping; drawn as they
are, a straight kilometre of road with its markings is thousands of triangles, and llvmpipe spends most of
a 320x240 frame transforming and setting up triangles, not filling pixels. A vertex is kept only where
leaving it out would move one of the lines (road edges, markings, kerbs) by more than a tolerance a
camera cannot see (1 cm is under a tenth of a pixel at 5 m on a 320 px wide image).
"""

from __future__ import annotations

import numpy as np

#: default tolerance (m): the largest distance a dropped vertex may lie from the chord that replaces it
SIMPLIFY_TOLERANCE_M = 0.01
#: default longest chord (m): the renderer cuts the static scene into 64 m tiles with a level of detail each
#: (lane markings only near the camera), so a triangle must not reach far beyond its tile
MAX_CHORD_M = 16.0


def _deviation(lines: np.ndarray, a: int, b: int) -> np.ndarray:
    """Largest distance over ``lines`` of each vertex strictly between a and b from the chord a-b."""
    p0, p1 = lines[:, a : a + 1], lines[:, b : b + 1]  # (K, 1, 3)
    seg = p1 - p0
    rel = lines[:, a + 1 : b] - p0  # (K, M, 3)
    seg_len2 = np.maximum((seg * seg).sum(axis=2, keepdims=True), 1e-12)
    t = np.clip((rel * seg).sum(axis=2, keepdims=True) / seg_len2, 0.0, 1.0)
    off = rel - t * seg
    return np.sqrt((off * off).sum(axis=2)).max(axis=0)


def simplify_indices(
    lines: np.ndarray, tolerance: float = SIMPLIFY_TOLERANCE_M, max_chord: float = MAX_CHORD_M
) -> np.ndarray:
    """Sorted indices of the vertices to keep so that every line of ``lines`` ((K, N, 3), K polylines
    sampled at the same N stations) stays within ``tolerance`` of its dense self and no chord is longer
    than ``max_chord``; both ends are kept."""
    lines = np.asarray(lines, np.float64)
    if lines.ndim == 2:
        lines = lines[None]
    n = lines.shape[1]
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        dev = _deviation(lines, a, b)
        i = int(np.argmax(dev))
        chord = float(np.sqrt(((lines[:, b] - lines[:, a]) ** 2).sum(axis=1)).max())
        if dev[i] > tolerance or chord > max_chord:
            m = a + 1 + i if dev[i] > tolerance else (a + b) // 2
            keep[m] = True
            stack.append((a, m))
            stack.append((m, b))
    return np.flatnonzero(keep)
