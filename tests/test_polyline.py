"""Road polylines are drawn with few vertices, and never more than a centimetre off their dense selves."""

from __future__ import annotations

import numpy as np

from genesis_rl.sim.lite.render.polyline import simplify_indices


def _max_deviation(line: np.ndarray, keep: np.ndarray) -> float:
    """Largest distance of any dense vertex from the simplified polyline's segment that spans it."""
    worst = 0.0
    for a, b in zip(keep[:-1], keep[1:], strict=True):
        p0, seg = line[a], line[b] - line[a]
        rel = line[a : b + 1] - p0
        t = np.clip(rel @ seg / max(float(seg @ seg), 1e-12), 0.0, 1.0)
        worst = max(worst, float(np.linalg.norm(rel - t[:, None] * seg, axis=1).max()))
    return worst


def test_a_straight_road_keeps_only_the_vertices_its_chord_limit_needs() -> None:
    s = np.arange(0.0, 200.0 + 1e-9, 0.5)  # 401 stations, 0.5 m apart as the maps sample them
    line = np.column_stack([s, np.zeros_like(s), np.zeros_like(s)])
    keep = simplify_indices(line, tolerance=0.01, max_chord=16.0)
    assert keep[0] == 0 and keep[-1] == len(s) - 1
    assert len(keep) <= 17  # 200 m in chords of at most 16 m
    assert np.diff(s[keep]).max() <= 16.0


def test_a_curve_on_a_hill_stays_within_tolerance_on_every_line() -> None:
    ang = np.arange(0.0, np.pi / 2, 0.5 / 60.0)  # a 60 m radius quarter turn, 0.5 m apart
    z = 3.0 * np.sin(ang * 4.0)  # and a hill
    lines = np.stack(
        [np.column_stack([r * np.cos(ang), r * np.sin(ang), z]) for r in (52.0, 60.0, 68.0)]
    )
    keep = simplify_indices(lines, tolerance=0.01)
    assert len(keep) < len(ang) / 2  # far fewer vertices...
    for line in lines:  # ...and each line within 1 cm of its dense self
        assert _max_deviation(line, keep) <= 0.01 + 1e-9
    loose = simplify_indices(lines, tolerance=0.10)
    assert len(loose) < len(keep)  # a looser tolerance keeps fewer


def test_short_lines_are_kept_whole() -> None:
    two = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert simplify_indices(two).tolist() == [0, 1]
