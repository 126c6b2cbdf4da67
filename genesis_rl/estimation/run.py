"""``genesis-rl estimate``'s driver: draws every episode from its seed, plays them on workers, adapts the
proposal between stages, checkpoints ``episodes.csv`` after every batch and writes ``estimate.json`` and
``estimate.png`` (docs/estimation.md).

Every draw happens here, from ``(seed, episode index)``: the scene, the episode seed, the start and the seed of
the step actions; the workers only play. So the same seed gives the same episodes and the same estimate with
any number of workers, and ``--resume`` continues from the episodes on disk (a stage's proposal is refit from
the stages before it, which are on disk too).
"""

from __future__ import annotations

import csv
import io
import math
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from genesis_rl.analysis.estimate_files import SCHEMA
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write, atomic_write_json
from genesis_rl.core.files.pins import Pins
from genesis_rl.core.files.spreadsheet import safe_rows
from genesis_rl.distributed.spawn_pool import SpawnPool
from genesis_rl.estimation import estimator
from genesis_rl.estimation.episodes import EpisodeTask, init_worker, run_task
from genesis_rl.estimation.nominal import NominalModel, StartRange, check_starts, default_starts
from genesis_rl.estimation.proposal import WIDEN_FINAL, StartProposal, elite

if TYPE_CHECKING:
    from genesis_rl.env.genesis_env import GenesisEnv

METHODS = ("crude", "importance")
#: episodes between checkpoints of episodes.csv
BATCH = 25
#: the cross-entropy refit's defaults: at least this many elite episodes (on latency_braking a 10-episode pilot's
#: 2-episode elite pulled the braking onto 4.5 +- 0.3 m/s^2 and the estimate's ESS to 6 of 40, docs/estimation.md),
#: and the new fit's weight against the proposal before (1: the fit alone; Rubinstein and Kroese's smoothing,
#: 0.4-0.9, slowed the toy of tests/test_estimation.py too much to be the default). Estimates started before 0.26
#: read as 1 and 1.0: the refit alone, as they ran
ELITE_MIN, SMOOTHING = 5, 1.0
#: failures found so far from which a refit uses them alone (pooled over the stages): a stage's elite by score
#: mixes in episodes that did not fail, whose larger ratios then outweigh the failures (on latency_braking the
#: first pilot's two failures, braking at 3.8-4.0 m/s^2 from 0.1-0.9 s, were outweighed by a late gentle
#: braking that scored high, and the proposal moved to 1.7 m/s^2 at 10 s, where nothing fails)
POOL_MIN = 2
#: what ranks a stage's episodes that did not fail, and the column that holds it: ``danger``, the largest inverse
#: time-to-collision to the lead (episodes.danger), or ``reward``, the episode's summed reward (before 0.26: on
#: latency_braking it ranked a gentle braking late in the episode above hard ones that nearly hit, and a pilot
#: without a failure sent the proposal where nothing fails)
SCORES = {"danger": "danger", "reward": "score"}
#: what the settings added in 0.26 meant for an estimate started before them (its refit ran this way)
SETTINGS_BEFORE_0_26 = {"elite_min": 1, "smoothing": 1.0, "tilt": None, "pool_failures": False, "score": "reward"}
#: which stages' episodes make an importance estimate: ``last``, the last stage alone (its proposal widened), or
#: ``adapted``, every stage whose proposal was refit (all but the first, broad one), pooled with weights fixed in
#: advance by their sizes, so the estimate stays unbiased (each stage's mean is unbiased given the stages before
#: it). Which is better depends on the problem (docs/estimation.md): on the braking toy (tests/test_estimation.py,
#: 300 seeds of 80 episodes) pooling gave 22.9x fewer episodes than crude Monte Carlo against 18.6x; on the sun
#: toy (100 seeds of 120) its spread was 0.47 of the truth against 0.29, the pilots' unwidened proposals weighing more
ESTIMATE_FROM = ("last", "adapted")
#: settings crude Monte Carlo does not use (a crude estimate resumes whatever they say)
IMPORTANCE_ONLY = ("elite", "elite_min", "smoothing", "tilt", "defensive", "pilot", "pool_failures", "score",
                   "estimate_from")
#: settings that only read the episodes (a resumed estimate may change them: the same episodes, read again)
READING_ONLY = ("estimate_from",)


@dataclass(frozen=True)
class EstimateSpec:
    """Everything that decides an estimate's episodes (``workers`` does not)."""

    member: str
    method: str
    episodes: int
    seed: int = 0
    steps: int | None = None  # None: the member's episode length
    stages: int = 4  # importance: stages; all but the last adapt the proposal (pilots), the last estimates
    pilot: float = 0.5  # importance: the share of the episodes the pilot stages take, split evenly
    defensive: float = 0.2  # importance: the nominal model's share of the proposal
    elite: float = 0.2  # importance: the share of a stage that refits the proposal
    elite_min: int = ELITE_MIN  # importance: the fewest episodes that refit it
    smoothing: float = SMOOTHING  # importance: the refit's weight against the proposal before (1: the fit alone)
    tilt: tuple[str, ...] | None = None  # importance: the start variables the proposal tilts (None: every one)
    pool_failures: bool = True  # importance: refit on every failure so far once there are POOL_MIN (else: scores)
    score: str = "danger"  # importance: what ranks the episodes that did not fail (SCORES)
    estimate_from: str = "last"  # importance: which stages make the estimate (ESTIMATE_FROM)
    catalog_seed: int = 0
    nominal: tuple[StartRange, ...] | None = None  # None: default_starts of the member's ODD
    weights: str | None = None  # the member's system with these detector weights (a hardened one); None: its own

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise UserInputError(f"--method = '{self.method}'; allowed: {', '.join(METHODS)}")
        if self.episodes < 1:
            raise UserInputError(f"--episodes = {self.episodes}; allowed: an integer >= 1")
        if self.steps is not None and self.steps < 1:
            raise UserInputError(f"--steps = {self.steps}; allowed: an integer >= 1 (or leave it out: the member's)")
        if not 1 <= self.stages <= self.episodes:
            raise UserInputError(f"--stages = {self.stages}; allowed: 1..--episodes ({self.episodes})")
        if not 0.0 < self.defensive <= 1.0:
            raise UserInputError(f"--defensive = {self.defensive}; allowed: a share in (0, 1] (0 would leave the "
                                 "weights unbounded where the proposal misses a failure region)")
        if not 0.0 < self.elite <= 1.0:
            raise UserInputError(f"--elite = {self.elite}; allowed: a share in (0, 1]")
        if self.elite_min < 1:
            raise UserInputError(f"--elite-min = {self.elite_min}; allowed: an integer >= 1")
        if not 0.0 < self.smoothing <= 1.0:
            raise UserInputError(f"--smoothing = {self.smoothing}; allowed: a weight in (0, 1] (1: the refit alone)")
        if self.estimate_from not in ESTIMATE_FROM:
            raise UserInputError(f"--estimate-from = '{self.estimate_from}'; allowed: {', '.join(ESTIMATE_FROM)}")
        if self.score not in SCORES:
            raise UserInputError(f"--score = '{self.score}'; allowed: {', '.join(SCORES)}")
        if self.tilt is not None and (not self.tilt or len(set(self.tilt)) != len(self.tilt)):
            raise UserInputError(f"--tilt = {','.join(self.tilt)}; allowed: start variables without repeats")
        if not 0.0 <= self.pilot < 1.0:
            raise UserInputError(f"--pilot = {self.pilot}; allowed: a share in [0, 1) (the last stage needs episodes)")
        if self.method == "importance" and self.stages > 1 and min(self.stage_sizes) < 1:
            raise UserInputError(f"--episodes {self.episodes} with --pilot {self.pilot} leaves a stage of "
                                 f"{self.stages} without an episode; give more episodes or fewer stages")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["nominal"] = None if self.nominal is None else {r.name: r.to_json() for r in self.nominal}
        d["tilt"] = None if self.tilt is None else list(self.tilt)
        return d

    @property
    def stage_sizes(self) -> list[int]:
        """Episodes per stage: the pilots share ``pilot`` of them evenly, the last stage takes the rest."""
        if self.method == "crude" or self.stages == 1:
            return [self.episodes]
        each = int(self.episodes * self.pilot) // (self.stages - 1)
        return [each] * (self.stages - 1) + [self.episodes - each * (self.stages - 1)]

    @property
    def estimate_stages(self) -> tuple[int, ...]:
        """The stages whose episodes make the estimate: every one of crude Monte Carlo or a single stage; the
        adapted stages (all but the broad first) or the last alone (``estimate_from``)."""
        last = len(self.stage_sizes) - 1
        if self.method == "crude" or last == 0:
            return (0,)
        return tuple(range(1, last + 1)) if self.estimate_from == "adapted" else (last,)

    @property
    def estimating_stage(self) -> int:
        """The last stage, whose proposal is widened (``estimate_stages``: the first pilot's broad proposal is
        never in the estimate: its few lucky failures, each weighing up to 1/defensive, would dominate it)."""
        return len(self.stage_sizes) - 1


def env_config(spec: EstimateSpec, catalog: Path) -> dict[str, Any]:
    from genesis_rl.sut.zoo.members import env_settings, zoo_member

    m = zoo_member(spec.member)
    env = env_settings(m)
    if spec.weights is not None:
        env["system_kwargs"] = {**env.get("system_kwargs", {}), "weights": str(Path(spec.weights).resolve())}
    return {**env, "catalog": str(catalog), "observation": "features", "episode_steps": steps_of(spec)}


def steps_of(spec: EstimateSpec) -> int:
    from genesis_rl.sut.zoo.members import zoo_member

    return spec.steps or int(zoo_member(spec.member).env.get("episode_steps", 512))


def nominal_model(spec: EstimateSpec, env: GenesisEnv) -> NominalModel:
    """The ``--nominal`` file's start ranges, else the default model of the member's ODD at its start weather."""
    held, dim = env.held_knobs, env.mapper.action_dim
    if spec.nominal is not None:
        return NominalModel(check_starts(spec.nominal, held, env.mapper.knobs), dim)
    return NominalModel(default_starts(held, env.odd, env.start_weather, env.conditions_model, env.mapper.knobs,
                                       steps_of(spec) * env.dt), dim)


def draw(spec: EstimateSpec, index: int, n_scenes: int, sample_start: Callable[[np.random.Generator], dict]
         ) -> EpisodeTask:
    """Episode ``index``: its scene, episode seed, start and step-action seed, all from ``(seed, index)``."""
    rng = np.random.default_rng([spec.seed, index, 0x5E57])
    scene = int(rng.integers(n_scenes))
    episode_seed = int(rng.integers(2**31 - 1))
    return EpisodeTask(index, scene, episode_seed, (spec.seed, index, 2), sample_start(rng))


def proposal_for(stage: int, rows: Sequence[dict[str, Any]], spec: EstimateSpec, nominal: NominalModel
                 ) -> StartProposal:
    """The proposal of ``stage``: the broad one, refit after each earlier stage on its elite (the estimating
    stage's widened by ``WIDEN_FINAL``)."""
    proposal = StartProposal.broad(nominal, spec.defensive, spec.tilt)
    for s in range(stage):
        pooled = [r for r in rows if int(r["stage"]) <= s and r["failed"]] if spec.pool_failures else []
        if len(pooled) >= POOL_MIN:
            # every failure found so far, each weighted by its own stage's ratio p/q: together they sample
            # p(start | failure), the proposal cross-entropy aims at, without the scores' noise
            picked_rows = pooled
        else:
            done = [r for r in rows if int(r["stage"]) == s]
            picked = elite([float(r[SCORES[spec.score]]) for r in done], [bool(r["failed"]) for r in done],
                           spec.elite, spec.elite_min)
            picked_rows = [done[i] for i in picked]
        starts = [start_of(r, nominal) for r in picked_rows]
        proposal = proposal.refit(starts, [math.exp(float(r["log_weight"])) for r in picked_rows], spec.smoothing)
    return proposal.widened(WIDEN_FINAL) if 0 < stage == spec.estimating_stage else proposal


def play_stages(spec: EstimateSpec, nominal: NominalModel, n_scenes: int, rows: list[dict[str, Any]],
                play: Callable[[Sequence[EpisodeTask]], Iterable[dict[str, Any]]], *,
                on_batch: Callable[[list[dict[str, Any]]], None] = lambda rows: None,
                on_episode: Callable[[], None] = lambda: None) -> list[dict[str, Any]]:
    """Draw and ``play`` every episode not in ``rows`` (appended, index order), stage by stage: each stage's
    proposal is refit on the stages before it. ``on_batch`` sees the rows after every batch (the checkpoint).
    Each row gains its stage and its log likelihood ratio of the start, log p - log q (the step actions are
    the nominal's under every proposal: their ratio is 1). Returns each stage's proposal and counts."""
    done = {r["index"] for r in rows}
    stages = []
    bounds = np.cumsum([0, *spec.stage_sizes])
    for stage in range(len(spec.stage_sizes)):
        proposal = proposal_for(stage, rows, spec, nominal) if spec.method == "importance" else None
        sample = proposal.sample if proposal else nominal.sample_start
        first, last = int(bounds[stage]), int(bounds[stage + 1])
        todo = [draw(spec, i, n_scenes, sample) for i in range(first, last) if i not in done]
        for b in range(0, len(todo), BATCH):
            batch = todo[b:b + BATCH]
            for task, row in zip(batch, play(batch), strict=True):
                log_p = nominal.start_log_density(task.start)
                log_q = proposal.log_pdf(task.start) if proposal else log_p
                rows.append({**row, "stage": stage, "log_weight": round(log_p - log_q, 10)})
                on_episode()
            rows.sort(key=lambda r: r["index"])
            on_batch(rows)
        stages.append({"stage": stage, "episodes": last - first,
                       "failures": sum(bool(r["failed"]) for r in rows if r["stage"] == stage),
                       "proposal": proposal.to_json() if proposal else "nominal"})
    return stages


def start_of(row: dict[str, Any], nominal: NominalModel) -> dict[str, float]:
    return {r.name: float(row[f"start_{r.name}"]) for r in nominal.starts}


# -- files ------------------------------------------------------------------------------------------------------

def read_rows(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    out = []
    with path.open(newline="", encoding="utf-8") as f:
        for line, r in enumerate(csv.DictReader(f), start=2):
            row: dict[str, Any] = dict(r)
            try:
                for k in ("index", "stage", "scene", "episode_seed", "steps", "in_odd_steps"):
                    row[k] = int(row[k])
                row["failed"] = row["failed"] == "True"
                row["fail_step"] = int(row["fail_step"]) if row["fail_step"] else None
                row["cluster"] = row["cluster"] or None
            except (KeyError, TypeError, ValueError) as err:  # an estimate of before the pins, damaged
                raise UserInputError(f"--resume: '{path}' line {line} is damaged ({type(err).__name__}: {err}); "
                                     "start again with --force") from None
            out.append(row)
    return out


def write_rows(path: Path, rows: Sequence[dict[str, Any]], pins: Pins | None = None) -> None:
    """The checkpoint ``episodes.csv``; pinned in the folder's ``pins.json`` when ``pins`` is given."""
    buf = io.StringIO()
    names = list(dict.fromkeys(k for r in rows for k in r))  # rows of an estimate from before a column: blank
    w = csv.DictWriter(buf, fieldnames=names, restval="", lineterminator="\n")
    w.writeheader()
    w.writerows(safe_rows(rows))
    if pins is not None:
        pins.write_bytes(path, buf.getvalue().encode("utf-8"))
    else:
        atomic_write(path, lambda p: p.write_text(buf.getvalue(), encoding="utf-8"))


@dataclass
class _Pool:
    """The workers (none: this process plays)."""

    env: dict[str, Any]
    steps: int
    workers: int

    def __enter__(self) -> _Pool:
        if self.workers > 1:
            self._pool = SpawnPool(self.workers, init_worker, (self.env, self.steps))
        else:
            init_worker(self.env, self.steps)
        return self

    def play(self, tasks: Sequence[EpisodeTask]) -> Iterator[dict[str, Any]]:
        if self.workers > 1:
            yield from self._pool.imap(run_task, tasks)
        else:
            yield from map(run_task, tasks)

    def __exit__(self, *exc: object) -> None:
        if self.workers > 1:
            self._pool.terminate()


def probe_member(spec: EstimateSpec, catalog: Path) -> tuple[NominalModel, int, float]:
    """The member's nominal model, scene count and step length, read off an env on ``catalog``; refuses a member
    without held knobs and a ``--tilt`` that names no start variable of it."""
    from genesis_rl.core.config import from_mapping
    from genesis_rl.env.genesis_env import EnvConfig, GenesisEnv

    probe = GenesisEnv(from_mapping(EnvConfig, env_config(spec, catalog), "env"))
    try:
        if not probe.held_knobs:
            raise UserInputError(f"member '{spec.member}': no knob is held within an episode, so the proposal "
                                 "has no start to tilt (estimate needs natural dynamics)")
        nominal = nominal_model(spec, probe)
        unknown = sorted(set(spec.tilt or ()) - {r.name for r in nominal.starts})
        if unknown:
            raise UserInputError(f"--tilt names {unknown}; allowed: this member's start variables "
                                 f"{[r.name for r in nominal.starts]}")
        return nominal, len(probe.catalog.scenes), probe.dt
    finally:
        probe.close()


def run_estimate(spec: EstimateSpec, out: Path, *, workers: int = 1, force: bool = False, resume: bool = False,
                 progress: bool = True) -> dict[str, Any]:
    """Play every episode not yet on disk, then write ``estimate.json`` and ``estimate.png``; the result."""
    from tqdm import tqdm

    from genesis_rl import __version__
    from genesis_rl.sim.backends import catalog_or_generate
    from genesis_rl.sim.lite.scenes import DEFAULT_COUNTS
    from genesis_rl.sut.zoo.members import zoo_member

    member = zoo_member(spec.member)
    out = Path(out)
    if resume and not (out / "estimate.json").exists():
        raise UserInputError(f"--resume: '{out}' holds no estimate.json; start it without --resume")
    with output_folder.claim(out, "estimate", force, resume=resume):
        if resume:
            found = output_folder.recorded_spec(out / "estimate.json", "estimate")
            # crude Monte Carlo may go on to more episodes (or stop at fewer); a field added since the estimate was
            # started reads as its default
            crude = spec.method == "crude" and found.get("method") == "crude"
            output_folder.check_same_settings(
                "estimate", out, found, spec.to_json(),
                may_change=("episodes", *IMPORTANCE_ONLY) if crude else READING_ONLY,
                defaults={**{f.name: f.default for f in fields(EstimateSpec) if f.default is not MISSING},
                          **SETTINGS_BEFORE_0_26})
            pins = Pins(out)
            # what the resume reuses instead of playing again: the scenes and the episodes played so far
            pins.check_or_record(out / "catalog.json")
            pins.check_or_record(out / "episodes.csv")
            nominal, n_scenes, dt = probe_member(spec, out / "catalog.json")
        else:
            catalog = catalog_or_generate(None, member.map, DEFAULT_COUNTS.get(member.map, 1), spec.catalog_seed,
                                          traffic=member.traffic)
            # the member and the settings are checked on a catalog outside --out, so that a refusal (a bad --tilt
            # name, a member without held knobs) leaves an estimate already there as it was, --force or not
            with tempfile.TemporaryDirectory(prefix="genesis-rl-estimate-") as tmp:
                catalog.save(Path(tmp) / "catalog.json")
                nominal, n_scenes, dt = probe_member(spec, Path(tmp) / "catalog.json")
                output_folder.replace(out, "estimate")
                pins = Pins.start(out)
                pins.write_bytes(out / "catalog.json", (Path(tmp) / "catalog.json").read_bytes())
        # unfinished until the end (a resumed one too: its spec may have gone on to more episodes)
        atomic_write_json(out / "estimate.json", {"schema": SCHEMA, "version": __version__,
                                                  "spec": spec.to_json(), "done": False}, indent=1)
        env_cfg = env_config(spec, out / "catalog.json")
        rows = [r for r in read_rows(out / "episodes.csv") if r["index"] < spec.episodes] if resume else []
        steps = steps_of(spec)
        bar = tqdm(total=spec.episodes, initial=len(rows), desc=f"estimate {spec.member} ({spec.method})",
                   unit="episode", disable=not progress)
        with _Pool(env_cfg, steps, workers) as pool:
            stages = play_stages(spec, nominal, n_scenes, rows, pool.play,
                                 on_batch=lambda done: write_rows(out / "episodes.csv", done, pins),
                                 on_episode=lambda: bar.update(1))
        bar.close()
        result = summarise(spec, rows, nominal, steps * dt, stages)
        atomic_write_json(out / "estimate.json", {"schema": SCHEMA, "version": __version__, "spec": spec.to_json(),
                                                  "done": True, **result}, indent=1)
        from genesis_rl.estimation.plot import plot_estimate

        plot_estimate(out / "estimate.png", rows, result, nominal)
        return result


def summarise(spec: EstimateSpec, rows: Sequence[dict[str, Any]], nominal: NominalModel, episode_s: float,
              stages: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The estimate (from ``spec.estimate_stages``), its diagnostics, the clusters that carry it and its
    convergence; ``episodes_spent`` counts every episode."""
    spent = len(rows)
    rows = [r for r in rows if int(r["stage"]) in spec.estimate_stages]
    failed = [bool(r["failed"]) for r in rows]
    log_w = [float(r["log_weight"]) for r in rows]
    est = estimator.crude(failed) if spec.method == "crude" else estimator.importance(failed, log_w)
    weights = np.exp(np.asarray(log_w))
    n = len(rows)
    clusters: dict[str, float] = {}
    counts: dict[str, int] = {}
    for r, w in zip(rows, weights, strict=True):
        if r["failed"]:
            key = str(r["cluster"])
            clusters[key] = clusters.get(key, 0.0) + float(w) / n
            counts[key] = counts.get(key, 0) + 1
    total = sum(clusters.values()) or 1.0
    by_cluster = [{"cluster": k, "failures": counts[k], "probability": v, "share": round(v / total, 4)}
                  for k, v in sorted(clusters.items(), key=lambda kv: -kv[1])]
    steps = np.array([r["steps"] for r in rows], np.float64)
    in_odd = float(np.sum(weights * np.array([r["in_odd_steps"] for r in rows]) / steps) / n)
    rhw = est.relative_half_width
    crude_needed = estimator.episodes_for(est.probability) if est.probability > 0 else None
    every = max(1, n // 100)
    return {"nominal": nominal.to_json(), "episode_s": episode_s, "estimate": est.to_json(),
            "per_hour": estimator.per_hour(est.probability, episode_s),
            "per_hour_ci95": [estimator.per_hour(v, episode_s) for v in est.ci95],
            "in_odd_share": round(in_odd, 4),
            "crude_episodes_for_0.3": None if crude_needed is None else round(crude_needed),
            "episodes_spent": spent,
            "episodes_ratio": None if crude_needed is None or rhw is None or rhw > 0.3 else
            round(crude_needed / spent, 1),
            "clusters": by_cluster, "stages": list(stages),
            "running": estimator.running(failed, None if spec.method == "crude" else log_w, every)}

