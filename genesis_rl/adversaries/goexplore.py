"""Go-Explore (``goexplore``): remember the states that were hard to reach, return to them exactly, explore on.

Go-Explore (Ecoffet et al., "First return, then explore", Nature 2021) keeps an archive of *cells*, coarse
descriptions of the states visited, each with the exact state that reached it first (or most dangerously); it
picks a cell (rarely chosen ones first, promising ones more often), returns to its state and explores from
there with random actions. Koren and Kochenderfer ("Adaptive Stress Testing without Domain Heuristics using
Go-Explore", ITSC 2020) found failures this way where Monte Carlo tree search and deep RL found none. The
searches here (``cmaes``, ``cem``, ``mcts``) replay whole episodes from the start; returning costs this one
about a tenth of a step (``GenesisEnv.snapshot``, exact to the bit).

A cell says what a tester would say matters: the sun's bearing from the heading and its altitude (in the
bands a photographer names: night, twilight, golden hour, low, high), whether it glares, the light, the
visibility and rain bands, the lead's gap and closing speed and whether the system sees it, each actor knob's
quarter of its range, and the quarter of the episode.

One search: where the campaign lets policies choose the start (``start = "natural"``), a root is first opened in
every stratum of the sun's start (its bearing in six 60 deg sectors, its altitude in the cells' bands) and
looked at for a few steps, the weather left as it starts, so that every kind of light is seen once. Then each
turn chooses a cell (half the time the most promising one, less so each time it is chosen; else a draw
weighted by novelty, promise and depth), returns to its snapshot and explores with held random actions, most
of them leaving the weather as it is; a quarter of the choices instead open a new root in the chosen cell's
stratum (one sun 3 deg up fails where 5 deg does not).

The objective is falsification: the search stops at the first in-ODD collision and reports it. A cell's promise
is the episode's worst danger so far (``loop.rules.danger``: the deceleration the ego would need to stop behind
its lead, over a hard braking's 6 m/s^2, more when the system misses a lead close ahead). The report is the
found action sequence replayed from the episode's start through the runner (one more episode, counted in the
budget), which gives the campaign its frames and checks that the return was exact; without a failure, the most
dangerous chain is replayed, the weather then held. The budget is ``search_budget`` episodes of simulator steps
per scene, as the searches'. Lite only: CARLA cannot save a world (its refusal says so).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from genesis_rl.adversaries.base import (
    EpisodeOutcome,
    EpisodeRunner,
    ExploringRunner,
    PolicyContext,
    SearchLedger,
    WeatherPolicy,
    chooses_start,
    in_odd_failure_at,
    register_policy,
)
from genesis_rl.core.errors import UserInputError
from genesis_rl.loop.rules.danger import danger
from genesis_rl.world.knobs import KNOBS, Weather
from genesis_rl.world.odd.domain import IN_ODD
from genesis_rl.world.step_record import StepRecord

#: the sun's altitude bands [deg]: night, nautical twilight, civil twilight, golden hour, low, mid, high
ALTITUDE_EDGES = (-12.0, -6.0, 0.0, 6.0, 12.0, 24.0, 48.0)
#: sectors of the sun's bearing from the heading: ahead, ahead-left/right, beside-behind left/right, behind
BEARING_SECTORS = 6
#: visibility bands [m] and rain bands [mm/h] of a cell
VISIBILITY_EDGES = (50.0, 100.0, 200.0, 500.0, 1000.0)
RAIN_EDGES = (0.1, 2.5, 7.6)
#: the lead's gap bands [m] and closing-speed bands [m/s] of a cell
GAP_EDGES = (5.0, 10.0, 20.0, 40.0, 80.0)
CLOSING_EDGES = (-1.0, 1.0, 3.0, 6.0)
#: how much a cell's danger counts in its choice against its novelty (at most 1.5)
PROMISE_WEIGHT = 1.0
#: quarters of the episode and of each actor knob's range
QUARTERS = 4


def _band(value: float, edges: tuple[float, ...]) -> int:
    return int(np.searchsorted(edges, value, side="right")) if math.isfinite(value) else -1


def bearing_sector(azimuth_deg: float, heading_deg: float) -> int:
    """The sun's sector seen from the heading: 0 straight ahead (within 30 deg), counting counter-clockwise."""
    bearing = (azimuth_deg - heading_deg) % 360.0
    return int(((bearing + 180.0 / BEARING_SECTORS) % 360.0) // (360.0 / BEARING_SECTORS))


def cell_of(rec: StepRecord, heading_deg: float, episode_steps: int, actor_knobs: tuple[str, ...]) -> Hashable:
    """The archive cell of a step (see the module docstring)."""
    k, c = rec.knobs, rec.conditions
    lead = rec.lead
    closing = rec.ego.speed - lead.speed if lead.present and math.isfinite(lead.speed) else math.nan
    return (
        bearing_sector(float(k.get("sun_azimuth_angle", 0.0)), heading_deg),
        _band(float(k.get("sun_altitude_angle", 90.0)), ALTITUDE_EDGES),
        None if c is None else (c.sun_glare, c.light, _band(c.visibility_m, VISIBILITY_EDGES),
                                _band(c.rain_mm_h, RAIN_EDGES), c.road_state),
        _band(lead.true_distance, GAP_EDGES) if lead.present else -2,
        _band(closing, CLOSING_EDGES),
        lead.detected,
        tuple(min(QUARTERS - 1, int((float(k[n]) - KNOBS[n].low) / KNOBS[n].span * QUARTERS)) for n in actor_knobs),
        min(QUARTERS - 1, rec.step * QUARTERS // max(episode_steps, 1)),
    )


@dataclass
class _Entry:
    """An archived cell: the exact state that reached it, how (the start and the actions from step 0), the
    danger on the way, and how often it was seen and chosen."""

    snapshot: object
    start: Weather | None
    actions: tuple[np.ndarray, ...]
    danger: float
    stratum: int  # the start's stratum (``GoExplore._strata``; -1: the start weather)
    seen: int = 1
    chosen: int = 0

    def weight(self, episode_steps: int) -> float:
        """Go-Explore's count-based choice (rarely chosen, rarely seen cells first) plus its promise: the danger
        so far and how far into the episode it lies (a failure needs time to build)."""
        return (1.0 / math.sqrt(1.0 + self.chosen) + 0.5 / math.sqrt(self.seen) + PROMISE_WEIGHT * self.danger
                + 0.5 * len(self.actions) / max(episode_steps, 1))


@register_policy
class GoExplore(WeatherPolicy):
    name = "goexplore"
    description = ("Go-Explore: an archive of cells (the sun's bearing and altitude, light, visibility, rain, the "
                   "lead's gap and closing speed, time), returned to from exact snapshots and explored from; "
                   "stops at the first in-ODD failure; search_budget episodes of steps per scene (lite only)")
    #: steps explored from a cell before choosing again, and how long a random action is held (Go-Explore's
    #: sticky actions: a knob turned for a while, not jittered)
    SEGMENT_STEPS = 48
    HOLD_STEPS = 12
    #: the share of held actions that leave the weather as it is: the world mostly stays, and a random turn
    #: of every knob at once would wash out the very condition a root was opened in
    KEEP_SHARE = 0.75
    #: the share of choices that return to the most promising cell rather than draw one
    EXPLOIT_SHARE = 0.5
    #: the share of choices of a cell that open a new root in its start's stratum instead of returning to it:
    #: within one kind of light, one start may fail where another does not (the sun 3 deg up, not 5)
    REROOT_SHARE = 0.25
    #: steps a new root is looked at, the weather left as it starts, before the archive's choice takes over
    LOOK_STEPS = 12

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        self.budget = int(context.options.get("search_budget", 8))
        if self.budget < 2:
            raise UserInputError(f"search_budget = {self.budget} must be >= 2 (goexplore replays what it found "
                                 "as one more episode)")
        from genesis_rl.core import limits

        limits.SEARCH_BUDGET.check(self.budget, "search_budget")

    @classmethod
    def episodes_per_scene(cls, options: dict[str, Any]) -> int:
        return int(options.get("search_budget", 8))

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        explorer = cast(ExploringRunner, runner)
        for needed in ("snapshot", "restore", "begin", "step"):
            if not callable(getattr(runner, needed, None)):
                raise UserInputError(f"goexplore needs a runner that returns to saved states; "
                                     f"{type(runner).__name__} has no {needed}()")
        steps = int(self.context.options.get("steps", 512))
        rng = np.random.default_rng([self.context.seed, scene, episode_seed, 0x60E])
        dim = self.context.action_dim
        actor_knobs = tuple(n for n in runner.knobs if KNOBS[n].is_actor)
        strata, draw = self._strata(explorer, scene, episode_seed, rng)
        archive: dict[Hashable, _Entry] = {}
        ledger = SearchLedger()
        spent, explore_budget = 0, (self.budget - 1) * steps  # the last episode's steps replay the report
        found: tuple[Weather | None, tuple[np.ndarray, ...]] | None = None
        opened = rerooted = 0
        while spent < explore_budget and found is None:
            stratum: int | None = None
            length = self.SEGMENT_STEPS
            if opened < len(strata):  # every stratum first, for a look: each kind of light once
                stratum, length = strata[opened], self.LOOK_STEPS
                opened += 1
            else:
                entry = self._choose(archive, steps, rng)
                if entry is None:  # every archived state lies at the episode's end (or none survived a crash)
                    break
                entry.chosen += 1
                if entry.stratum >= 0 and rng.random() < self.REROOT_SHARE:
                    stratum = entry.stratum  # a promising kind of light, from another start inside it
                    rerooted += 1
                else:
                    explorer.restore(entry.snapshot)
                    start, actions, worst, root = entry.start, entry.actions, entry.danger, entry.stratum
            if stratum is not None:
                start, actions, worst, root = draw(stratum), (), 0.0, stratum
                explorer.begin(scene, episode_seed, start)
            records: list[StepRecord] = []
            action = np.zeros(dim, np.float32)  # a new root is looked at as it starts
            for t in range(min(length, steps - explorer.steps_taken, explore_budget - spent)):
                if t % self.HOLD_STEPS == 0 and stratum is None:  # a knob turned for a while, or left as it is
                    action = rng.uniform(-1.0, 1.0, dim).astype(np.float32) if rng.random() >= self.KEEP_SHARE \
                        else np.zeros(dim, np.float32)
                rec = explorer.step(action)
                records.append(rec)
                actions = (*actions, action)
                spent += 1
                if rec.collision.collided:
                    if rec.odd_status in IN_ODD:
                        found = (start, actions)
                    break  # a crashed ego explores nothing more
                worst = max(worst, danger(rec))
                cell = cell_of(rec, explorer.heading_deg, steps, actor_knobs)
                known = archive.get(cell)
                if known is None or worst > known.danger or (worst == known.danger and
                                                             len(actions) < len(known.actions)):
                    archive[cell] = _Entry(explorer.snapshot(), start, actions, worst, root,
                                           seen=1 + (known.seen if known else 0),
                                           chosen=known.chosen if known else 0)
                else:
                    known.seen += 1
            if records:
                ledger.add(EpisodeOutcome(records, sim_steps=len(records)), value=-math.inf)
        chain = found or self._most_dangerous(archive) or (draw(0), ())
        report = runner.run(_replay(chain[1], dim), scene, episode_seed, chain[0])
        ledger.add(report, value=math.inf)
        replayed_at = in_odd_failure_at(report.records)
        return ledger.report(archive_cells=len(archive), strata=len(strata), rerooted=rerooted,
                             found_at_step=None if found is None else len(found[1]) - 1,
                             replay_exact=None if found is None else replayed_at == len(found[1]) - 1)

    def _strata(self, runner: ExploringRunner, scene: int, episode_seed: int, rng: np.random.Generator
                ) -> tuple[list[int], Callable[[int], Weather | None]]:
        """The strata new roots open in, in a seeded order (one per cell of the sun's start: its bearing sector
        and altitude band, other held knobs drawn anywhere in their range; one, the start weather, when the
        campaign does not let policies choose), and a draw of a start inside a stratum."""
        held = runner.held_knobs
        if not (chooses_start(self.context.options) and held):
            return [-1], lambda stratum: None
        runner.begin(scene, episode_seed, None)
        heading = runner.heading_deg  # the scene's, before any step: the weather does not turn the ego
        per_knob = [range(BEARING_SECTORS) if n == "sun_azimuth_angle" else
                    range(len(ALTITUDE_EDGES) + 1) if n == "sun_altitude_angle" else range(1) for n in held]
        cells = list(itertools.product(*per_knob))

        def draw(stratum: int) -> Weather | None:
            position = [self._inside(n, int(i), heading, rng) for n, i in zip(held, cells[stratum], strict=True)]
            return runner.start_from(position)

        return [int(i) for i in rng.permutation(len(cells))], draw

    @staticmethod
    def _inside(knob: str, stratum: int, heading: float, rng: np.random.Generator) -> float:
        """A uniform draw inside ``stratum`` of ``knob``, as the 0..1 position ``start_from`` takes."""
        spec = KNOBS[knob]
        if knob == "sun_azimuth_angle":
            width = 360.0 / BEARING_SECTORS
            bearing = stratum * width + rng.uniform(-width / 2.0, width / 2.0)
            value = spec.fit(heading + bearing)
        elif knob == "sun_altitude_angle":
            edges = (spec.low, *ALTITUDE_EDGES, spec.high)
            value = rng.uniform(edges[stratum], edges[stratum + 1])
        else:  # another held knob (a short episode holds the slow ones too): anywhere in its range
            value = spec.low + rng.uniform() * spec.span
        return (value - spec.low) / spec.span

    @classmethod
    def _choose(cls, archive: dict[Hashable, _Entry], steps: int, rng: np.random.Generator) -> _Entry | None:
        """Half the time the most promising cell (the most dangerous, less so each time it is chosen), else a
        draw weighted by novelty and promise: with a few dozen cells of steady driving, a draw alone would
        return to the one dangerous cell once in twenty tries."""
        entries = [e for e in archive.values() if len(e.actions) < steps]
        if not entries:
            return None
        dangerous = [e for e in entries if e.danger > 0.0]
        if dangerous and rng.random() < cls.EXPLOIT_SHARE:
            return max(dangerous, key=lambda e: (e.danger / math.sqrt(1.0 + e.chosen), len(e.actions)))
        weights = np.array([e.weight(steps) for e in entries])
        return entries[int(rng.choice(len(entries), p=weights / weights.sum()))]

    @staticmethod
    def _most_dangerous(archive: dict[Hashable, _Entry]) -> tuple[Weather | None, tuple[np.ndarray, ...]] | None:
        if not archive:
            return None
        best = max(archive.values(), key=lambda e: (e.danger, len(e.actions)))
        return best.start, best.actions


def _replay(actions: tuple[np.ndarray, ...], dim: int) -> Callable[[Any], np.ndarray]:
    """The found actions from the episode's start, then the knobs held (a zero action) to its end."""
    state = {"t": 0}
    hold = np.zeros(dim, np.float32)

    def act(obs: Any) -> np.ndarray:
        t = state["t"]
        state["t"] += 1
        return actions[t] if t < len(actions) else hold

    return act
