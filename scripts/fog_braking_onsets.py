"""fog_braking's ground truth, which a one-knob sweep cannot show: the order of two events.

For each onset, every scene is driven with the fog thickening from the member's start at its natural rate
(4 %/s, from ~150 m toward 50 m of visibility) from the first step and the lead's braking demand rising at its
natural rate (4 m/s^2 a second) to 6 m/s^2 from the onset; ``--held`` holds the fog at 50 m from the first step
instead. Prints the collisions per onset. docs/zoo.md gives the table this printed.

    .venv/bin/python scripts/fog_braking_onsets.py fog_braking --onsets 0,1,2,4 --scenes 8
    .venv/bin/python scripts/fog_braking_onsets.py adaptive_braking --onsets 1,2,4 --scenes 8
    .venv/bin/python scripts/fog_braking_onsets.py fog_braking --onsets 0 --held --scenes 8
"""

from __future__ import annotations

import argparse
import time

from genesis_rl.loop.drive import run_episode
from genesis_rl.sim.lite.backend import LiteBackend
from genesis_rl.sim.lite.scenes import generate_catalog
from genesis_rl.sut.system.protocol import load_system
from genesis_rl.sut.zoo import zoo_member
from genesis_rl.sut.zoo.timing import fog_then_brake


def _onsets(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}': give a comma list of seconds, e.g. 0,1,2,4") from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("member", choices=("fog_braking", "adaptive_braking"))
    parser.add_argument("--onsets", type=_onsets, default="0,1,2,4",
                        help="seconds after the fog begins that the lead brakes, a comma list")
    parser.add_argument("--scenes", type=int, default=8)
    parser.add_argument("--steps", type=int, default=256)
    parser.add_argument("--held", action="store_true", help="fog held at 50 m from the first step")
    parser.add_argument("--rain", action="store_true",
                        help="rain setting in with the fog at its natural rate (2 %%/s), as a constant schedule's")
    args = parser.parse_args()
    member = zoo_member(args.member)
    catalog = generate_catalog("highway", args.scenes, 0, traffic=member.traffic)
    with LiteBackend() as backend:
        for onset in args.onsets:
            weather = fog_then_brake(str(member.env["start_weather"]), onset, 0.05, held=args.held, rain=args.rain)
            t0, hits = time.monotonic(), []
            for i in range(args.scenes):
                system = load_system(member.system, **member.system_kwargs)
                result = run_episode(backend, catalog.scene(i), system, weather, args.steps, seed=i,
                                     stop_on_collision=True)
                first = next((r.step for r in result.records if r.collision.collided), None)
                hits.append(first)
            failed = sum(h is not None for h in hits)
            fog = ("fog held at 50 m" if args.held else "fog thickening") + (" with rain" if args.rain else "")
            print(f"{args.member} {fog}, lead braking from "
                  f"{onset:g} s: {failed}/{args.scenes} collided, first steps {hits} "
                  f"({time.monotonic() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
