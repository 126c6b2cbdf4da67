"""Which vehicle the ``lead_decel`` knob would brake, switched on at any of an episode's first 2 s.

For 50 free-flow highway scenes of catalog seed 0, the ego coasting (no system steers it), each of the first 40
ticks: the corridor leader (``Traffic.lead``, the knob's old choice) and ``Traffic.lead_in_lane`` (its choice
now), against the nearest vehicle ahead along the ego's lane and the lane after it. Prints in how many scenes
each rule would have braked another vehicle at least once.

    .venv/bin/python scripts/lead_decel_choice.py
"""

from __future__ import annotations

from genesis_rl.sim.lite.backend import LiteBackend
from genesis_rl.sim.lite.scenes import generate_catalog
from genesis_rl.sim.lite.traffic import LEAD_RANGE, Traffic

SCENES, TICKS = 50, 40


def nearest_in_lane(t: Traffic) -> int | None:
    """The nearest vehicle ahead along the ego's lane and the lane after it, by distance along the lanes."""
    lanes = (int(t.lane[0]), int(t.next_lane[0]))
    best: tuple[float, int] | None = None
    for j in range(1, t.n):
        if int(t.lane[j]) == lanes[0] and t.s[j] > t.s[0]:
            ahead = float(t.s[j] - t.s[0])
        elif int(t.lane[j]) == lanes[1] != lanes[0]:
            ahead = float(t.map.length[lanes[0]] - t.s[0] + t.s[j])
        else:
            continue
        gap = ahead - 0.5 * float(t.length[0] + t.length[j])
        if gap < LEAD_RANGE and (best is None or gap < best[0]):
            best = (gap, j)
    return None if best is None else best[1]


def main() -> None:
    catalog = generate_catalog("highway", SCENES, 0, traffic="free_flow")
    backend = LiteBackend()
    wrong = {"corridor (old)": 0, "lead_in_lane (now)": 0}
    for scene in catalog.scenes:
        with backend.create_simulation(scene, seed=scene.seed, render=False) as sim:
            t = sim.traffic
            missed = {name: False for name in wrong}
            for _ in range(TICKS):
                truth = nearest_in_lane(t)
                for name, choice in (("corridor (old)", t.lead()), ("lead_in_lane (now)", t.lead_in_lane())):
                    missed[name] |= choice is not None and choice.vehicle_id != truth
                sim.tick()
            for name in wrong:
                wrong[name] += missed[name]
    for name, count in wrong.items():
        print(f"{name}: would brake another vehicle than the lead in {count} of {SCENES} scenes")


if __name__ == "__main__":
    main()
