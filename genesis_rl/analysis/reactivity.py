"""Does the adversary react to what it sees? Closed-loop results against the same actions played open-loop.

A policy that reacts to the scene (raises the fog as the lead brakes) does better on the scene it watched
than its own action sequence does when played blind elsewhere. A policy that plays a fixed schedule (a
constant corner) does exactly as well either way. For each scene i, with its campaign episode seed s_i:

- **other scene**: the policy plays (i, s_i) closed-loop; its actions from scene i+1 (cyclically) are played
  open-loop on (i, s_i). The gap is closed-loop minus open-loop, per scene.
- **other seed**: the policy plays (i, s'_i) closed-loop, and its actions from (i, s_i) are played open-loop
  on (i, s'_i): the same scene, other traffic randomness.

Open-loop actions go through the same env step (the naturalness limit and the ODD's projection apply), and
step k plays the k-th recorded action. Metrics per episode: the policy's return (what it maximises), whether
the ego collided and the collision violation. Gaps come with bootstrap CIs and sign-flip p-values
(:func:`genesis_rl.core.stats.paired_comparison`). The simulator is deterministic per (scene, episode
seed), so a constant policy's gap is exactly zero.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from tqdm import tqdm

from genesis_rl.core.stats import paired_comparison
from genesis_rl.world.step_record import StepRecord

#: the default metrics of an episode, from its step records
METRICS: dict[str, Callable[[Sequence[StepRecord]], float]] = {
    "reward": lambda recs: float(sum(r.reward["reward"] for r in recs)),  # what the adversary maximises
    "collided": lambda recs: float(any(r.collision.collided for r in recs)),
    "collision": lambda recs: float(sum(r.rules.get("collision", 0.0) for r in recs)),  # the rule's violation
}
Metrics = dict[str, Callable[[Sequence[StepRecord]], float]]
KINDS = ("other_scene", "other_seed")


class ActingPolicy(Protocol):
    """What the measurement needs of a policy: a reset per episode and an action per observation (the
    campaign's step policies have both)."""

    def reset(self, scene: int, episode_seed: int) -> None: ...

    def act(self, obs: Any) -> np.ndarray: ...


@dataclass(frozen=True)
class EpisodeScore:
    """An episode's metrics by name."""

    values: dict[str, float]

    def metric(self, name: str) -> float:
        return self.values[name]


@dataclass(frozen=True)
class PairRow:
    """One scene's closed-loop and open-loop episode of one kind."""

    kind: str
    scene: int
    episode_seed: int
    donor_scene: int  # the scene whose actions the open-loop episode played
    donor_seed: int
    closed: EpisodeScore
    open: EpisodeScore


def _score(env: Any, metrics: Metrics) -> EpisodeScore:
    return EpisodeScore({name: float(fn(env.records)) for name, fn in metrics.items()})


def _steps(env: Any) -> int:
    """Actions an episode takes: its steps, and the start step of an env with a start head (the open-loop
    episode plays the donor's start action too, so the pair differs in reacting only)."""
    return int(env.config.episode_steps) + int(getattr(env.config, "start_head", False))


def play_closed(env: Any, policy: ActingPolicy, scene: int, episode_seed: int,
                metrics: Metrics = METRICS) -> tuple[EpisodeScore, np.ndarray]:
    """The policy plays the episode; returns its score and its actions (steps x knobs)."""
    policy.reset(scene, episode_seed)
    obs, _ = env.reset(options={"scene": scene, "episode_seed": episode_seed})
    actions = []
    for _ in range(_steps(env)):
        a = np.asarray(policy.act(obs), np.float32)
        actions.append(a)
        obs, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            break
    return _score(env, metrics), np.asarray(actions, np.float32)


def play_open(env: Any, actions: np.ndarray, scene: int, episode_seed: int, metrics: Metrics = METRICS) -> EpisodeScore:
    """``actions`` played blind, step k the k-th (the last one held if the episode is longer)."""
    env.reset(options={"scene": scene, "episode_seed": episode_seed})
    for k in range(_steps(env)):
        _, _, terminated, truncated, _ = env.step(actions[min(k, len(actions) - 1)])
        if terminated or truncated:
            break
    return _score(env, metrics)


@dataclass
class ReactivityResult:
    rows: list[PairRow]
    seed: int
    metrics: tuple[str, ...] = tuple(METRICS)

    def gap(self, kind: str, metric: str) -> dict[str, Any]:
        """Closed-loop minus open-loop over the scenes: mean with CI, wins/ties/losses, p-value."""
        rows = [r for r in self.rows if r.kind == kind]
        return paired_comparison([r.closed.metric(metric) for r in rows], [r.open.metric(metric) for r in rows],
                                 self.seed)

    def summary(self) -> dict[str, Any]:
        return {kind: {m: self.gap(kind, m) for m in self.metrics} for kind in KINDS
                if any(r.kind == kind for r in self.rows)}

    def to_json(self) -> dict[str, Any]:
        return {"seed": self.seed, "gaps": self.summary(), "rows": [asdict(r) for r in self.rows]}


class Player(Protocol):
    """Plays a measurement's episodes, in the order asked (here, or on a pool of workers)."""

    def closed(self, jobs: Sequence[tuple[int, int]]) -> list[tuple[EpisodeScore, np.ndarray]]: ...

    def open(self, jobs: Sequence[tuple[np.ndarray, int, int]]) -> list[EpisodeScore]: ...


@dataclass
class LocalPlayer:
    """This process plays every episode on ``env`` with ``policy``."""

    env: Any
    policy: ActingPolicy
    metrics: Metrics
    bar: Any = None

    def closed(self, jobs: Sequence[tuple[int, int]]) -> list[tuple[EpisodeScore, np.ndarray]]:
        return [self._tick(play_closed(self.env, self.policy, s, e, self.metrics)) for s, e in jobs]

    def open(self, jobs: Sequence[tuple[np.ndarray, int, int]]) -> list[EpisodeScore]:
        return [self._tick(play_open(self.env, a, s, e, self.metrics)) for a, s, e in jobs]

    def _tick(self, x: Any) -> Any:
        if self.bar is not None:
            self.bar.update()
        return x


def measure(env: Any, policy: ActingPolicy, scenes: Sequence[int], episode_seeds: Sequence[int],
            other_seeds: Sequence[int] | None = None, seed: int = 0, progress: bool = False,
            metrics: Metrics = METRICS) -> ReactivityResult:
    """The reactivity gaps of ``policy`` on ``scenes`` (at least 2) with their campaign ``episode_seeds``;
    ``other_seeds`` (one per scene) adds the other-seed comparison. 2 episodes per scene, 4 with other seeds.
    ``metrics``: name -> function of an episode's step records (default :data:`METRICS`)."""
    _check(scenes, episode_seeds, other_seeds)
    bar = tqdm(total=len(scenes) * (4 if other_seeds is not None else 2), desc="reactivity", unit="episode",
               disable=not progress)
    try:
        return measure_with(LocalPlayer(env, policy, metrics, bar), scenes, episode_seeds, other_seeds, seed,
                            tuple(metrics))
    finally:
        bar.close()


def _check(scenes: Sequence[int], episode_seeds: Sequence[int], other_seeds: Sequence[int] | None = None) -> None:
    if len(scenes) < 2 or len(scenes) != len(episode_seeds):
        raise ValueError("reactivity needs >= 2 scenes, each with its episode seed")
    if other_seeds is not None and len(other_seeds) != len(scenes):
        raise ValueError("reactivity's other seeds: one per scene")


def measure_with(player: Player, scenes: Sequence[int], episode_seeds: Sequence[int],
                 other_seeds: Sequence[int] | None, seed: int, metrics: tuple[str, ...]) -> ReactivityResult:
    """The measurement in two rounds, each a batch of independent episodes (so a pool can play a round in
    parallel): every closed-loop episode, then every open-loop one, which needs the closed-loop actions. An
    episode is fixed by its scene and episode seed, so the rows are the same however the rounds are played."""
    scenes, episode_seeds = [int(s) for s in scenes], [int(e) for e in episode_seeds]
    _check(scenes, episode_seeds, other_seeds)
    n = len(scenes)
    others = [int(o) for o in other_seeds] if other_seeds is not None else []
    closed = player.closed([*zip(scenes, episode_seeds, strict=True),
                            *zip(scenes if others else [], others, strict=True)])
    mine, on_other_seed = closed[:n], closed[n:]
    donor = [(i + 1) % n for i in range(n)]
    opens = player.open([(mine[donor[i]][1], scenes[i], episode_seeds[i]) for i in range(n)]
                        + [(mine[i][1], scenes[i], others[i]) for i in range(len(others))])
    rows = [PairRow("other_scene", scenes[i], episode_seeds[i], scenes[donor[i]], episode_seeds[donor[i]],
                    mine[i][0], opens[i]) for i in range(n)]
    rows += [PairRow("other_seed", scenes[i], others[i], scenes[i], episode_seeds[i], on_other_seed[i][0],
                     opens[n + i]) for i in range(len(others))]
    return ReactivityResult(rows, seed, metrics)


# -- a pool of workers, each with its own env and policy (the default metrics: lambdas do not pickle) ------
_WORKER: dict[str, Any] = {}


def _init_worker(spec_json: dict[str, Any], folder: str, policy_name: str, plugins: Sequence[str]) -> None:
    """Build this worker's env and policy (a failure reaches the parent through the first episode: SpawnPool)."""
    import torch

    from genesis_rl.adversaries import resolve_policy
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.campaigns.episodes import CampaignRunner
    from genesis_rl.core.plugins import import_modules

    import_modules(plugins, checked=False)  # what the parent imported, through its gate
    torch.set_num_threads(1)
    spec = CampaignSpec.from_json(spec_json)
    env = CampaignRunner(spec, Path(folder)).env
    _WORKER.update(env=env, policy=resolve_policy(policy_name)(spec.policy_context(env.mapper.action_dim)))


def _closed_task(job: tuple[int, int]) -> tuple[EpisodeScore, np.ndarray]:
    return play_closed(_WORKER["env"], _WORKER["policy"], job[0], job[1])


def _open_task(job: tuple[np.ndarray, int, int]) -> EpisodeScore:
    return play_open(_WORKER["env"], job[0], job[1], job[2])


@dataclass
class PoolPlayer:
    """``workers`` spawned processes play each round, in order (``imap``), with the campaign's env."""

    spec_json: dict[str, Any]
    folder: str
    policy_name: str
    workers: int
    plugins: tuple[str, ...] = ()
    bar: Any = None

    def __enter__(self) -> PoolPlayer:
        from genesis_rl.distributed.spawn_pool import SpawnPool

        self._pool = SpawnPool(self.workers, _init_worker, (self.spec_json, self.folder, self.policy_name,
                                                            self.plugins))
        return self

    def __exit__(self, *exc: object) -> None:
        self._pool.terminate()

    def closed(self, jobs: Sequence[tuple[int, int]]) -> list[tuple[EpisodeScore, np.ndarray]]:
        return self._round(_closed_task, jobs)

    def open(self, jobs: Sequence[tuple[np.ndarray, int, int]]) -> list[EpisodeScore]:
        return self._round(_open_task, jobs)

    def _round(self, fn: Callable[[Any], Any], jobs: Sequence[Any]) -> list[Any]:
        out = []
        for x in self._pool.imap(fn, jobs):
            out.append(x)
            if self.bar is not None:
                self.bar.update()
        return out


def other_seed(campaign_seed: int, scene: int) -> int:
    """The other-seed comparison's episode seed of ``scene``: drawn from the campaign seed, never the
    campaign's own (pick_scenes draws that from [seed, scene])."""
    return int(np.random.default_rng([campaign_seed, scene, 17]).integers(0, 2**31 - 1))


def measure_campaign(folder: Any, policy_name: str, scenes: int | None = None, with_other_seeds: bool = True,
                     progress: bool = True, workers: int = 1) -> ReactivityResult:
    """The reactivity gaps of a campaign's step policy (``agent``, ``constant``, ``random``, or a user's) on
    the campaign's scenes and episode seeds (its first ``scenes`` of them), in the campaign's env; with
    ``workers`` > 1 on a pool of processes (the same rows)."""
    from genesis_rl.adversaries import StepPolicy, resolve_policy
    from genesis_rl.campaigns.campaign_files import read_campaign_meta
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.campaigns.episodes import CampaignRunner
    from genesis_rl.core.errors import UserInputError

    folder = Path(folder)
    saved = read_campaign_meta(folder)  # checked: a damaged campaign.json is named, not a traceback
    spec = CampaignSpec.from_json(saved["spec"])
    pairs = [tuple(p) for p in saved["scenes"]]
    if scenes is not None:
        if not 2 <= scenes <= len(pairs):
            raise UserInputError(f"--scenes = {scenes}; allowed: 2..{len(pairs)} (the campaign's scenes)")
        pairs = pairs[:scenes]
    cls = resolve_policy(policy_name)
    if not issubclass(cls, StepPolicy):
        raise UserInputError(f"--policy '{policy_name}' searches over episodes; reactivity needs a step policy "
                             "(agent, constant, random, sunny or your own StepPolicy)")
    if cls.needs_agent and not spec.agent:  # reactivity has no --agent: the campaign names the agent
        raise UserInputError(f"--policy '{policy_name}': campaign '{folder}' was evaluated without an agent; "
                             "choose a campaign made with `genesis-rl evaluate --agent runs/NAME`")
    idx = [int(s) for s, _ in pairs]
    seeds = [int(e) for _, e in pairs]
    others = [other_seed(spec.seed, s) for s in idx] if with_other_seeds else None
    if workers > 1:
        from genesis_rl.campaigns.worker import plugin_modules

        bar = tqdm(total=len(idx) * (4 if others is not None else 2), desc="reactivity", unit="episode",
                   disable=not progress)
        try:
            most = len(idx) * (2 if others is not None else 1)  # the larger round's episodes: no idle env
            with PoolPlayer(saved["spec"], str(folder), policy_name, min(workers, most), tuple(plugin_modules()),
                            bar) as pool:
                return measure_with(pool, idx, seeds, others, spec.seed, tuple(METRICS))
        finally:
            bar.close()
    runner = CampaignRunner(spec, folder)
    try:
        policy = cls(spec.policy_context(runner.env.mapper.action_dim))
        return measure(runner.env, policy, idx, seeds, others, seed=spec.seed, progress=progress)
    finally:
        runner.close()
