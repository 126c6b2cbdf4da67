"""Competence of the built-in system in the conditions its detector was trained for (slow: ~3 min).

The full figure (50 seeded highway test scenes) is measured with
``genesis-rl drive --map highway --scene 0:50 --out DIR`` and given in docs/system.md; this test drives
the first 10 of them for the full 512 steps while the lead vehicles brake and stop now and then.
"""

from __future__ import annotations

import pytest

from genesis_rl.loop.drive import run_episode
from genesis_rl.sim.lite.backend import LiteBackend
from genesis_rl.sim.lite.scenes import generate_catalog
from genesis_rl.sut.system.protocol import load_system
from genesis_rl.world.knobs import Weather

pytestmark = [pytest.mark.slow, pytest.mark.render]


def test_builtin_system_drives_clear_noon_highway_scenes_without_collision() -> None:
    catalog = generate_catalog("highway", 10, seed=0)
    system = load_system("builtin")
    collided, lead_stops = [], 0
    with LiteBackend() as backend:
        for scene in catalog.scenes:
            result = run_episode(backend, scene, system, lambda _: Weather.preset("clear_noon"), 512, seed=0)
            if any(r.collision.collided for r in result.records):
                collided.append(scene.index)
            lead_stops += any(r.lead.present and r.lead.speed < 0.5 for r in result.records)
    assert len(collided) <= 1, f"collisions in scenes {collided}"
    assert lead_stops >= 3  # the ego met a stopped vehicle ahead in several scenes and did not hit it
