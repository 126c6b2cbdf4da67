"""The ground truth of a reactive zoo member: does reacting matter there, measured rather than argued.

A member is *reactive* when its weakness opens at a moment the world draws, so that an adversary must watch
the system to hit it. Two policies measure that on the member (``adversaries.scripted``):

- the scripted reactive policy written from the mechanism (``stall_watcher``), played on held-out scenes and
  world seeds;
- the best fixed schedule: ``fixed_onset`` at every onset of a grid, each played on the tuning scenes (world
  seeds apart from the held-out ones), the onset with the most counted failures kept (ties: the earliest) and
  played on the held-out ones.

A failure *counts* as the benchmark's confirmed ones do: in the ODD, triggered (at or after the episode first
entered the trigger region) and not blamed unavoidable (when the tester braked the vehicle hit, the R157
careful driver in the ego's place avoids it). A member passes when the reactive policy's failures count in at
least :data:`REACTIVE_AT_LEAST` of the held-out episodes and the best fixed schedule's in at most
:data:`FIXED_AT_MOST` (docs/zoo.md). The triggered shares, blame aside, are kept beside them. The grid spends
``len(onsets) * tuning`` episodes, ten times and more the 8 a search spends on a scene by default.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.stats import clopper_pearson

#: what "reacting matters" means on a member: the reactive policy's least and the fixed schedule's most
#: triggered share on held-out episodes
REACTIVE_AT_LEAST, FIXED_AT_MOST = 0.60, 0.15
#: the members whose mechanism has a scripted reactive policy, and its name
WATCHERS = {"stall_braking": "stall_watcher"}
#: seed-sequence tags of the two splits' world seeds, so that tuning and held-out worlds never meet
TUNING, HELD_OUT = 0x7E57, 0x401D


@dataclass(frozen=True)
class Episode:
    """One episode's outcome: where it first entered the trigger region and first failed inside the ODD."""

    policy: str
    onset_s: float | None
    scene: int
    world_seed: int
    reached_at: int | None
    failure_at: int | None
    #: the failure's blame is "unavoidable" (the careful driver collides too); None: no failure
    unavoidable: bool | None = None

    @property
    def triggered(self) -> bool:
        return self.failure_at is not None and self.reached_at is not None and self.failure_at >= self.reached_at

    @property
    def counts(self) -> bool:
        """Triggered and avoidable: what the benchmark confirms (re-runs aside: the truth plays each world once)."""
        return self.triggered and not self.unavoidable


def world_seeds(seed: int, split: int, count: int) -> list[int]:
    """``count`` world seeds of one split (TUNING or HELD_OUT), drawn from ``seed``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), split]))
    return [int(v) for v in rng.integers(0, 2**31 - 1, count)]


_WORKER: dict[str, Any] = {}


def _init(member: str, folder: str, seed: int) -> None:
    import torch

    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.campaigns.episodes import CampaignRunner
    from genesis_rl.core.threads import INFERENCE_THREADS
    from genesis_rl.sut.zoo.members import env_settings, zoo_member

    torch.set_num_threads(INFERENCE_THREADS)
    m = zoo_member(member)
    steps = int(m.env.get("episode_steps", 512))
    spec = CampaignSpec(policies=("sunny",), map=m.map, scenes=1, seed=seed, steps=steps,
                        env={**env_settings(m), "terminate_on_collision": True}, traffic=m.traffic)
    _WORKER.update(member=m, runner=CampaignRunner(spec, Path(folder)), seed=seed)


def _play(task: tuple[str, float | None, int, int]) -> Episode:
    from genesis_rl.adversaries import PolicyContext, resolve_policy
    from genesis_rl.adversaries.base import in_odd_failure_at

    name, onset, scene, world_seed = task
    runner, m = _WORKER["runner"], _WORKER["member"]
    options = {} if onset is None else {"onset_s": onset}
    policy = resolve_policy(name)(PolicyContext(runner.env.mapper.action_dim, _WORKER["seed"], options=options))
    outcome = policy.run_episode(runner.in_world(world_seed), scene, world_seed)
    failure_at = in_odd_failure_at(outcome.records)
    reached_at = m.trigger.reached(outcome.records)
    if failure_at is None:
        return Episode(name, onset, scene, world_seed, reached_at, None)

    def oracle() -> bool:
        return runner.oracle_collides(scene, world_seed, outcome.records, failure_at, outcome.start)

    return Episode(name, onset, scene, world_seed, reached_at, failure_at,
                   unavoidable(outcome, failure_at, runner.env.dt, oracle))


def unavoidable(outcome: Any, hit_at: int, dt: float, oracle_collides: Callable[[], bool]) -> bool:
    """The campaign's blame of the failure at ``hit_at`` (``campaigns.episodes``): with a careful-driver
    reference (the tester acted on the vehicle hit) unavoidable when that driver collides too; else as the
    visibility evidence and the counterfactual oracle replay say, which is played only then (a perception
    failure is avoidable)."""
    from genesis_rl.labels.blame import blame_label, visibility_evidence
    from genesis_rl.labels.careful_driver import careful_driver_evidence, event_for_collision

    records = outcome.records
    event = event_for_collision(outcome.actor_events, records, hit_at)
    careful = None if event is None else careful_driver_evidence(records, hit_at, event, dt)
    oracle = None if careful is not None else oracle_collides()
    return blame_label(visibility_evidence(records, hit_at, dt), oracle, careful) == "unavoidable"


def _share(episodes: Sequence[Episode]) -> dict[str, Any]:
    """The counted share (``share``, ``ci95``) and, blame aside, the triggered one."""
    k, n = sum(e.counts for e in episodes), len(episodes)
    t = sum(e.triggered for e in episodes)
    ci, ci_t = clopper_pearson(k, n), clopper_pearson(t, n)
    return {"counted": k, "episodes": n, "share": round(k / n, 4) if n else None,
            "ci95": [ci["ci_low"], ci["ci_high"]], "triggered": t,
            "triggered_share": round(t / n, 4) if n else None, "triggered_ci95": [ci_t["ci_low"], ci_t["ci_high"]],
            "unavoidable": sum(bool(e.unavoidable) for e in episodes),
            "failed": sum(e.failure_at is not None for e in episodes),
            "reached": sum(e.reached_at is not None for e in episodes)}


def measure(member: str, *, tuning: int = 6, held_out: int = 30, onsets: Sequence[float] = (), seed: int = 0,
            workers: int = 1, progress: bool = True) -> dict[str, Any]:
    """The member's reactivity ground truth (module docstring); tuning scenes are 0..tuning-1 of the member's
    generated catalog, held-out scenes the next ``held_out``, each split with its own world seeds."""
    from genesis_rl.campaigns.layout import CampaignFolder
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.sut.zoo.members import zoo_member

    if member not in WATCHERS:
        raise UserInputError(f"zoo member '{member}' has no scripted reactive policy; allowed: {', '.join(WATCHERS)}")
    m = zoo_member(member)
    steps = int(m.env.get("episode_steps", 512))
    grid = tuple(onsets) or tuple(float(t) for t in np.arange(0.0, steps * 0.05 - 4.0, 1.0))
    tune_seeds, held_seeds = world_seeds(seed, TUNING, tuning), world_seeds(seed, HELD_OUT, held_out)
    with tempfile.TemporaryDirectory(prefix="genesis-rl-truth-") as tmp:
        generate_catalog(m.map, tuning + held_out, seed, traffic=m.traffic).save(CampaignFolder(Path(tmp)).catalog)
        tune = [("fixed_onset", t, i, s) for t in grid for i, s in enumerate(tune_seeds)]
        held = [(WATCHERS[member], None, tuning + i, s) for i, s in enumerate(held_seeds)]
        ctx = get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(member, tmp, seed)) as pool:
            bar = tqdm(total=len(tune) + 2 * len(held), desc=f"truth {member}", unit="episode", disable=not progress)
            tuned = _collect(pool, tune, bar)
            by_onset = {t: [e for e in tuned if e.onset_s == t] for t in grid}
            best = max(grid, key=lambda t: (sum(e.counts for e in by_onset[t]), -t))
            fixed = [("fixed_onset", best, tuning + i, s) for i, s in enumerate(held_seeds)]
            played = _collect(pool, held + fixed, bar)
            bar.close()
    reactive = [e for e in played if e.onset_s is None]
    fixed_eps = [e for e in played if e.onset_s is not None]
    r, f = _share(reactive), _share(fixed_eps)
    return {
        "member": member, "seed": seed, "tuning_episodes": len(tune), "held_out_episodes": held_out,
        "onsets_s": list(grid), "tuning_counted_by_onset": {f"{t:g}": sum(e.counts for e in by_onset[t])
                                                            for t in grid},
        "best_fixed_onset_s": best, "reactive": r, "best_fixed": f,
        "reactive_policy": WATCHERS[member],
        "passes": bool(r["share"] is not None and f["share"] is not None and r["share"] >= REACTIVE_AT_LEAST
                       and f["share"] <= FIXED_AT_MOST),
        "episodes": [asdict(e) | {"triggered": e.triggered, "counts": e.counts} for e in (*tuned, *played)],
    }


def _collect(pool: ProcessPoolExecutor, tasks: list, bar: tqdm) -> list[Episode]:
    out = []
    for episode in pool.map(_play, tasks):
        out.append(episode)
        bar.update()
    return out


def plot_truth(result: dict[str, Any], path: Path) -> None:
    """Two panels: the tuning scenes' counted failures at each fixed onset (the search the best schedule came
    from), and the held-out counted shares of the reactive policy and the best fixed schedule with their 95 %
    intervals against the thresholds; a hollow marker shows each triggered share, blame aside."""
    from genesis_rl.core.files.io_utils import atomic_write
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()
    fig, (grid, held) = plt.subplots(1, 2, figsize=(9.0, 3.2), gridspec_kw={"width_ratios": [1.6, 1.0]})
    onsets = [float(t) for t in result["onsets_s"]]
    counts = [result["tuning_counted_by_onset"][f"{t:g}"] for t in onsets]
    per = result["tuning_episodes"] // max(len(onsets), 1)
    grid.bar(onsets, counts, width=0.8, color="#8c8c8c")
    grid.bar([result["best_fixed_onset_s"]], [result["tuning_counted_by_onset"][f"{result['best_fixed_onset_s']:g}"]],
             width=0.8, color="#d62728", label=f"best: {result['best_fixed_onset_s']:g} s")
    grid.set_xlim(min(onsets) - 1.0, max(onsets) + 1.0)  # one onset alone would fill the panel with its bar
    grid.set_xlabel("fixed onset of the lead's braking [s]")
    grid.set_ylabel(f"counted of {per} tuning episodes")
    grid.set_ylim(0, max(per, 1))
    grid.set_yticks(range(max(per, 1) + 1))
    grid.legend(fontsize=8)
    grid.set_title(f"{result['member']}: fixed schedules on tuning worlds", fontsize=9)
    names = [result["reactive_policy"], f"fixed_onset {result['best_fixed_onset_s']:g} s"]
    for k, (cell, color) in enumerate(((result["reactive"], "#1f77b4"), (result["best_fixed"], "#d62728"))):
        lo, hi = cell["ci95"]
        held.errorbar([k], [cell["share"]], yerr=[[cell["share"] - lo], [hi - cell["share"]]], fmt="o", color=color,
                      capsize=4)
        held.annotate(f"{cell['counted']}/{cell['episodes']}", (k, cell["share"]), xytext=(8, -3),
                      textcoords="offset points", fontsize=8)
        if cell["triggered_share"] != cell["share"]:  # failures blamed unavoidable: triggered, not counted
            held.plot([k], [cell["triggered_share"]], "o", mfc="none", color=color,
                      label="triggered, blame aside" if k == 0 else None)
            held.annotate(f"{cell['triggered']}/{cell['episodes']} triggered", (k, cell["triggered_share"]),
                          xytext=(8, -3), textcoords="offset points", fontsize=7, color="#555555")
    held.axhline(REACTIVE_AT_LEAST, color="#1f77b4", ls=":", lw=1)
    held.axhline(FIXED_AT_MOST, color="#d62728", ls=":", lw=1)
    held.annotate(f"reactive needs >= {REACTIVE_AT_LEAST:.2f}", (1.45, REACTIVE_AT_LEAST), xytext=(0, 3),
                  textcoords="offset points", fontsize=7, ha="right", color="#1f77b4")
    held.annotate(f"fixed must stay <= {FIXED_AT_MOST:.2f}", (1.45, FIXED_AT_MOST), xytext=(0, 3),
                  textcoords="offset points", fontsize=7, ha="right", color="#d62728")
    held.set_xticks([0, 1], names, fontsize=8)
    held.set_xlim(-0.5, 1.5)
    held.set_ylim(-0.02, 1.02)
    held.set_ylabel("counted share, held-out worlds")
    if held.get_legend_handles_labels()[0]:
        held.legend(fontsize=7, loc="upper center")
    held.set_title(f"{result['held_out_episodes']} held-out scenes and worlds", fontsize=9)
    fig.tight_layout()
    atomic_write(Path(path), lambda p: fig.savefig(p, format="png", dpi=110))
    plt.close(fig)
