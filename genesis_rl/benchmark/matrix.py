"""``genesis-rl benchmark``: every adversary on every zoo member over repeated trials.

The matrix is members x trials campaigns, each playing every policy on the member's map inside its ODD
(``zoo.members.env_settings``) with its own seed (``seed + trial``: other scenes, other episode seeds), so a
trial is a repetition as ARCH-COMP's 10 falsification runs are. The benchmark sits above ``evaluation``: it
runs campaigns with ``run_campaign`` (local processes or Ray, resumable), and campaigns do not know it. Its
folder::

    OUT/benchmark.json                       the spec (what decides the results)
    OUT/campaigns/MEMBER/trial_NN/           one campaign each (campaign.json, episodes/, summary.json, ...)
    OUT/campaigns/MEMBER/trial_NN_tuning/    under ``--protocol transfer``: the searches on the trial's tuning
                                             scenes; trial_NN/ then holds the held-out scenes (``benchmark.transfer``)
    OUT/leaderboard.json, leaderboard.html   the figures (``benchmark.leaderboard``)

``--resume`` continues the matrix where it stopped: finished campaigns are kept, a half-run one resumes
from its finished episodes, so the figures are those of an uninterrupted run.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from tqdm import tqdm

from genesis_rl.benchmark.campaign_once import finished, run_campaign_once
from genesis_rl.benchmark.reproduce import DEFAULT_RERUNS, reproduction_file, run_reproductions
from genesis_rl.benchmark.transfer import DEFAULT_TUNING_SCENES, SEARCHES, tuned
from genesis_rl.campaigns.campaign_folder import check_finished_campaign
from genesis_rl.campaigns.campaign_spec import CampaignSpec
from genesis_rl.core import limits
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write_json
from genesis_rl.core.signals import set_resume_hint
from genesis_rl.sut.zoo.members import ZOO, env_settings, zoo_member

SCHEMA = "genesis-rl/benchmark"
#: a trial count beyond this is refused (each is a campaign per member)
MAX_TRIALS = 100
#: re-runs of a reported failure beyond this are refused (each is an episode)
MAX_RERUNS = 100
#: how adversaries are scored: on the scenes they searched, or on held-out scenes after tuning elsewhere
PROTOCOLS = ("per_scene", "transfer")
#: the adversaries a benchmark plays; a trained agent needs one training per member, which this command does not do
ADVERSARIES = ("sunny", "random", "constant", "random_search", "corner_search", "cmaes", "cem", "mcts", "goexplore",
               "stall_watcher", "verifai_ce", "verifai_mab", "verifai_bo")


@dataclass(frozen=True)
class BenchmarkSpec:
    """What decides a benchmark's results: the members, the policies, how many trials (campaign seeds), how
    many scenes a trial plays per policy, the first seed, the steps per episode (None: each member's own) and
    the policies' options (``search_budget``, ``constant_action``, ...)."""

    members: tuple[str, ...]
    policies: tuple[str, ...]
    trials: int = 10
    scenes: int = 5
    seed: int = 0
    steps: int | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    #: where episodes start: "natural" (each adversary chooses the knobs that cannot move within an
    #: episode, so a weakness of the sun's position can be reached) or "fixed" (``evaluate --start``)
    start: str = "natural"
    #: trained agents by member: each a run folder (one training seed), played as the policy ``agent:RUN``
    #: (RUN the folder's name) in a campaign of its own per trial, on the trial's scenes and seeds
    agents: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    #: re-runs of every reported in-ODD failure on fresh world seeds (``benchmark.reproduce``); 0: none, and the
    #: primary score then asks no reproduction
    reruns: int = DEFAULT_RERUNS
    #: ``per_scene`` (every adversary searches the scene it is scored on) or ``transfer`` (searches are tuned on
    #: other scenes and replay their best schedule on held-out ones: ``benchmark.transfer``)
    protocol: str = "per_scene"
    #: under ``transfer``: the tuning scenes of each trial, none of them held out
    tuning_scenes: int = DEFAULT_TUNING_SCENES

    def __post_init__(self) -> None:
        for name, values, allowed in (("members", self.members, tuple(ZOO)),
                                      ("policies", self.policies, ADVERSARIES)):
            if not values:
                raise UserInputError(f"benchmark {name}: empty; allowed: {', '.join(allowed)}")
            unknown = [v for v in values if v not in allowed]
            if unknown:
                hint = " (an agent needs one training per member: train it and evaluate it on the member)" \
                    if "agent" in unknown else ""
                raise UserInputError(f"benchmark {name}: {unknown} unknown; allowed: {', '.join(allowed)}{hint}")
            if len(set(values)) != len(values):
                raise UserInputError(f"benchmark {name}: {list(values)} names one twice")
        for name, value, low, high in (("trials", self.trials, 1, MAX_TRIALS), ("scenes", self.scenes, 1, None),
                                       ("seed", self.seed, 0, 2**31 - 1), ("reruns", self.reruns, 0, MAX_RERUNS)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low or \
                    (high is not None and value > high):
                raise UserInputError(f"benchmark {name} = {value!r}; allowed: an integer in {low}.."
                                     f"{high if high is not None else 'the scene limit'}")
        limits.SCENES.check(self.scenes, "benchmark scenes")
        labels: list[str] = []
        for member, runs in self.agents.items():
            if member not in self.members:
                raise UserInputError(f"benchmark agents: member '{member}' is not among the members "
                                     f"({', '.join(self.members)})")
            if not runs:
                raise UserInputError(f"benchmark agents: member '{member}' names no run folder")
            labels += [f"{member}/{agent_label(r)}" for r in runs]
        if len(set(labels)) != len(labels):
            raise UserInputError(f"benchmark agents: {labels} names one run twice (folders of one name)")
        if self.protocol not in PROTOCOLS:
            raise UserInputError(f"benchmark protocol = {self.protocol!r}; allowed: {', '.join(PROTOCOLS)}")
        if not isinstance(self.tuning_scenes, int) or isinstance(self.tuning_scenes, bool) or self.tuning_scenes < 1:
            raise UserInputError(f"benchmark tuning_scenes = {self.tuning_scenes!r}; allowed: an integer >= 1")
        limits.SCENES.check(self.tuning_scenes, "benchmark tuning_scenes")
        if self.protocol == "transfer" and not tuned(self.policies):
            raise UserInputError(f"benchmark protocol transfer: none of the policies {list(self.policies)} is a "
                                 f"search to tune; name at least one of {', '.join(SEARCHES)}")
        if self.start not in ("fixed", "natural"):
            raise UserInputError(f"benchmark start = {self.start!r}; allowed: fixed, natural")
        if self.steps is not None:
            if not isinstance(self.steps, int) or isinstance(self.steps, bool) or self.steps < 1:
                raise UserInputError(f"benchmark steps = {self.steps!r}; allowed: an integer >= 1, or none "
                                     "(each member's own episode length)")
            limits.SIM_STEPS.check(self.steps, "benchmark steps")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(members=list(self.members), policies=list(self.policies), options=dict(self.options))
        if self.agents:  # written only when given, so benchmark.json files of before compare unchanged
            d["agents"] = {m: list(r) for m, r in self.agents.items()}
        else:
            del d["agents"]
        if self.protocol == "per_scene":  # written only for transfer, so benchmark.json files of before compare
            del d["protocol"], d["tuning_scenes"]
        return d


def agent_label(run: str) -> str:
    """The policy name of a trained agent in the leaderboard: ``agent:`` and its run folder's name, and for a
    checkpoint the checkpoint's too (``agent:RUN/step_00020480``), so seeds compared at one step stay apart."""
    from genesis_rl.adversaries.agent import run_folder_of

    path = Path(run)
    folder = run_folder_of(path).resolve().name
    if path.suffix == ".zip" and path.parent.name == "checkpoints":
        return f"agent:{folder}/{path.stem}"
    return f"agent:{folder}"


#: the env fields of a trained agent's run that a campaign on a member takes from it: what it observes (and
#: whether its first action chooses the start)
AGENT_OBSERVATION_KEYS = ("observation", "obs_history", "obs_width", "obs_height", "obs_knobs", "start_head",
                          "start_action")
#: the env fields a trained agent must share with the member it is benchmarked on (its action space and world)
AGENT_MATCH_KEYS = ("system", "system_kwargs", "knobs", "dynamics")


#: ``--smoke``: the whole pipeline in about a minute on 2 cores, with a pair built to fail so that its
#: metrics have values to check: ``constant`` (+1 on every knob) makes latency_braking's lead brake as hard as the
#: domain allows from the first step, which its late perception meets too late on trial 0's scene (trial 1's ego
#: meets it in time); ``sunny`` never brakes the lead; builtin_braking (the same controller without the latency) is
#: the control, met in time
SMOKE = BenchmarkSpec(members=("latency_braking", "builtin_braking"), policies=("sunny", "constant"), trials=2,
                      scenes=1, steps=160, reruns=2)


def member_steps(spec: BenchmarkSpec, member: str) -> int:
    """Steps per episode on ``member``: the spec's, else the member's own, else 512."""
    return spec.steps or int(zoo_member(member).env.get("episode_steps", 512))


def campaign_spec(spec: BenchmarkSpec, member: str, trial: int,
                  agent: tuple[str, dict[str, Any]] | None = None) -> CampaignSpec:
    """The campaign of one trial on one member: every adversary, or with ``agent`` (a run folder and the env
    ``agent_env`` gave it) that trained agent alone, on the same scenes and seeds."""
    m = zoo_member(member)
    options = {**spec.options, **({"start": spec.start} if spec.start != "fixed" else {})}
    run, env = agent if agent is not None else (None, env_settings(m))
    return CampaignSpec(policies=spec.policies if run is None else ("agent",), map=m.map, scenes=spec.scenes,
                        seed=spec.seed + trial, steps=member_steps(spec, member), agent=run, env=env, options=options,
                        traffic=m.traffic)


def campaign_folder(out: Path, member: str, trial: int) -> Path:
    """A trial's campaign (under ``transfer``: its held-out scenes)."""
    return Path(out) / "campaigns" / member / f"trial_{trial:02d}"


def tuning_folder(out: Path, member: str, trial: int) -> Path:
    """A trial's tuning campaign under ``transfer``."""
    return Path(out) / "campaigns" / member / f"trial_{trial:02d}_tuning"


def tuning_campaign_spec(spec: BenchmarkSpec, member: str, trial: int) -> CampaignSpec:
    """A trial's tuning campaign: its searches on ``tuning_scenes`` scenes none of which the trial holds out."""
    from genesis_rl.benchmark.transfer import held_out_scenes, tuning_spec

    held = campaign_spec(spec, member, trial)
    return tuning_spec(held, spec.tuning_scenes, held_out_scenes(held))


def held_out_campaign_spec(spec: BenchmarkSpec, out: Path, member: str, trial: int) -> CampaignSpec:
    """A trial's held-out campaign under ``transfer``: every search replays its best tuning schedule."""
    from genesis_rl.benchmark.transfer import best_schedule, held_out_spec

    region = zoo_member(member).trigger
    folder = tuning_folder(out, member, trial)
    return held_out_spec(campaign_spec(spec, member, trial),
                         {p: best_schedule(folder, p, region)[0] for p in tuned(spec.policies)})


def agent_campaign_folder(out: Path, member: str, trial: int, run: str) -> Path:
    name = agent_label(run).replace(":", "_").replace("/", "_")
    return Path(out) / "campaigns" / member / f"trial_{trial:02d}_{name}"


def agent_env(member: str, run: str) -> dict[str, Any]:
    """The env a trained agent plays ``member`` under: the member's, with what the agent observes taken from its
    run. A run trained on another system, other knobs or other dynamics is refused, naming the field: its
    figures would be reported as the member's."""
    from genesis_rl.campaigns.campaign_spec import env_settings_for
    from genesis_rl.env.genesis_env import EnvConfig
    from genesis_rl.world.odd.domain import load_odd

    m = zoo_member(member)
    trained = env_settings_for(run, None, None)
    wanted = env_settings(m)
    defaults = {f.name: f.default if f.default is not MISSING else f.default_factory()  # type: ignore[operator]
                for f in fields(EnvConfig) if f.name in AGENT_MATCH_KEYS}
    for key in AGENT_MATCH_KEYS:
        have, want = trained.get(key, defaults[key]), wanted.get(key, defaults[key])
        if key == "knobs":
            have, want = list(have or ()), list(want or ())
        if key == "system_kwargs":  # one weights file, however its path is spelled (the pins check its bytes)
            have, want = _same_weights_spelling(have), _same_weights_spelling(want)
        if have != want:
            raise UserInputError(f"benchmark agent '{run}' was trained with env.{key} = {have!r}; zoo member "
                                 f"'{member}' has {want!r}: train it on the member's env (docs/zoo.md)")
    odd = trained.get("odd")
    if odd is None or load_odd(odd).name != load_odd(m.odd_path).name:
        raise UserInputError(f"benchmark agent '{run}' was trained with env.odd = {odd!r}; zoo member '{member}' "
                             f"plays inside '{m.odd}': train it inside the member's ODD")
    return {**wanted, **{k: trained[k] for k in AGENT_OBSERVATION_KEYS if k in trained},
            "terminate_on_collision": False}


def _same_weights_spelling(kwargs: Any) -> Any:
    """``system_kwargs`` with its ``weights`` path resolved: a run trained with the shipped weights named from
    the repository (``genesis_rl/sut/zoo/weights/...``) plays the member that names them by absolute path."""
    if isinstance(kwargs, dict) and isinstance(kwargs.get("weights"), str):
        return {**kwargs, "weights": str(Path(kwargs["weights"]).resolve())}
    return kwargs


def _check_same_spec(out: Path, spec: BenchmarkSpec) -> None:
    found = output_folder.recorded_spec(out / "benchmark.json", "benchmark")
    wanted = spec.to_json()
    # agents may be added to a benchmark (their campaigns are new; nothing run changes), not taken away
    before = {m: list(r) for m, r in (found.get("agents") or {}).items()}
    now = wanted.get("agents") or {}
    dropped = [f"{m}: {r}" for m, runs in before.items() for r in runs if r not in now.get(m, [])]
    if dropped:
        raise UserInputError(f"--resume: benchmark '{out}' has agents {dropped} that --agent leaves out; name "
                             "them again, or start again with --force")
    output_folder.check_same_settings("benchmark", out, found, wanted, may_change=("agents",))


#: how a benchmark's workers share its matrix: ``episodes`` (each campaign in turn, its episodes over the
#: workers), ``campaigns`` (whole campaigns side by side, one process or Ray actor each: benchmark.parallel,
#: benchmark.ray_campaigns), or ``auto``
PARALLEL = ("auto", "campaigns", "episodes")


def check_parallel(parallel: str) -> None:
    """Refuse a ``--parallel`` that is not one of PARALLEL, whatever is left to run."""
    if parallel not in PARALLEL:
        raise UserInputError(f"--parallel = '{parallel}'; allowed: {', '.join(PARALLEL)}")


def parallel_mode(parallel: str, workers: int, executor: Any, campaigns: int) -> str:
    """``auto``: campaigns side by side (local processes or Ray actors, each sending its campaign's files back
    so that a cluster needs no shared folder) when there are at least two campaigns a worker to run (fewer
    leave a worker idle at the end for longer than a campaign's set-up costs); episodes otherwise. One local
    worker runs in this process (episodes); one Ray worker takes campaigns, so that the matrix starts Ray and
    its actor once, not once a campaign."""
    check_parallel(parallel)
    if campaigns <= 1 or (workers <= 1 and (executor is None or parallel == "episodes")):
        return "episodes"
    if parallel == "auto":
        return "campaigns" if campaigns >= 2 * workers else "episodes"
    return parallel


def run_benchmark(spec: BenchmarkSpec, out: Path, *, force: bool = False, resume: bool = False,
                  workers: int = 1, executor: Any = None, progress: bool = True,
                  estimates: Mapping[str, Path] | None = None, parallel: str = "auto") -> dict[str, Any]:
    """Run every (member, trial) campaign not yet finished, then write the leaderboard; returns it.
    ``parallel``: how ``workers`` share the matrix (:func:`parallel_mode`); the figures are the same either way.
    ``estimates``: per member, a finished ``genesis-rl estimate`` folder whose rate the page shows beside the
    failures found (read first: a wrong one is refused before any episode runs)."""
    from genesis_rl import __version__
    from genesis_rl.analysis.estimate_files import load_estimate
    from genesis_rl.benchmark.leaderboard import leaderboard, write_leaderboard

    out = Path(out)
    if resume and not (out / "benchmark.json").exists():
        raise UserInputError(f"--resume: '{out}' holds no benchmark.json; start it without --resume")
    check_parallel(parallel)  # before the folder is touched
    if executor is not None:
        executor.preflight()  # Ray installed and its address answering, before the folder is touched
    # each agent's env, once: a run trained elsewhere is refused before the folder is touched
    agent_envs = {(m, r): agent_env(m, r) for m, runs in spec.agents.items() for r in runs}
    unknown = sorted(set(estimates or {}) - set(spec.members))
    if unknown:
        raise UserInputError(f"--estimate names member(s) {unknown} that this benchmark does not play; its members: "
                             f"{', '.join(spec.members)}")
    rates = {m: load_estimate(Path(f), m) for m, f in (estimates or {}).items()}
    with output_folder.claim(out, "benchmark", force, resume=resume):
        if resume:
            _check_same_spec(out, spec)
        else:
            output_folder.replace(out, "benchmark")  # only genesis-rl's own entries go (--force)
        atomic_write_json(out / "benchmark.json", {"schema": SCHEMA, "version": __version__,
                                                   "spec": spec.to_json()}, indent=1)
        cells: list[tuple[str, int, str | None]] = [
            (m, t, run) for m in spec.members for t in range(spec.trials) for run in (None, *spec.agents.get(m, ()))]
        if spec.protocol == "transfer":  # the searches tune on scenes of their own first
            _run_jobs([(tuning_campaign_spec(spec, m, t), tuning_folder(out, m, t))
                       for m in spec.members for t in range(spec.trials)],
                      out, "tuning", workers, executor, parallel, progress)
        jobs = [(_trial_spec(spec, out, m, t) if run is None else campaign_spec(spec, m, t, (run, agent_envs[m, run])),
                 campaign_folder(out, m, t) if run is None else agent_campaign_folder(out, m, t, run))
                for m, t, run in cells]
        _run_jobs(jobs, out, "benchmark" if spec.protocol == "per_scene" else "held-out scenes", workers, executor,
                  parallel, progress)
        if spec.reruns:
            done = [(f, m, t) for (m, t, run), (_, f) in zip(cells, jobs, strict=True)]
            again = [(f, m, zoo_member(m).trigger, t, reproduction_file(out, m, f)) for f, m, t in done]
            rbar = tqdm(total=len(again), desc="re-runs on fresh worlds", unit="campaign", disable=not progress)
            rbar.update(sum(Path(j[4]).is_file() for j in again))
            try:
                run_reproductions(again, spec.seed, spec.reruns, workers, on_done=lambda target: rbar.update())
            except KeyboardInterrupt as err:
                set_resume_hint(err, f"the campaigns and finished re-runs in '{out}' are kept; the same command with "
                                     "--resume runs the rest")
                raise
            rbar.close()
        board = leaderboard(spec.to_json(), {m: member_trials(spec, out, m) for m in spec.members},
                            {m: {agent_label(r): [agent_campaign_folder(out, m, t, r) for t in range(spec.trials)]
                                 for r in runs} for m, runs in spec.agents.items()}, out=out)
        board["estimates"] = rates
        if spec.protocol == "transfer":
            board["transfer"] = transfer_summary(spec, out, board)
        write_leaderboard(out, board)
    return board


def transfer_summary(spec: BenchmarkSpec, out: Path, board: Mapping[str, Any]) -> dict[str, Any]:
    """Under transfer, per member: each policy's simulator steps (tuning, training, held-out, in all), the
    schedule each search took from its tuning scenes in each trial, and the trained agents' break-even counts
    of held-out scenes against each search (``benchmark.transfer``)."""
    from genesis_rl.adversaries.agent import trained_steps
    from genesis_rl.benchmark.transfer import (
        best_schedule,
        break_even_table,
        campaign_steps,
        held_out_scenes,
        seen_in_training,
        transfer_costs,
    )

    members: dict[str, Any] = {}
    for m in spec.members:
        region = zoo_member(m).trigger
        tuning = [campaign_steps(tuning_folder(out, m, t)) for t in range(spec.trials)]
        held: list[dict[str, int]] = []
        for t in range(spec.trials):
            steps = campaign_steps(campaign_folder(out, m, t))
            for run in spec.agents.get(m, ()):
                steps[agent_label(run)] = campaign_steps(agent_campaign_folder(out, m, t, run))["agent"]
            held.append(steps)
        costs = transfer_costs(tuning, held, {agent_label(r): trained_steps(Path(r)) for r in spec.agents.get(m, ())})
        trial_specs = [campaign_spec(spec, m, t) for t in range(spec.trials)]
        seen = {agent_label(r): [seen_in_training(r, c, held_out_scenes(c)) for c in trial_specs]
                for r in spec.agents.get(m, ())}
        members[m] = {
            "costs": costs,
            "held_out_scenes_seen_in_training": {a: None if None in v else sum(v) for a, v in seen.items()},
            "tuned": {p: [best_schedule(tuning_folder(out, m, t), p, region)[1] for t in range(spec.trials)]
                      for p in tuned(spec.policies)},
            "break_even_scenes": break_even_table(board["cells"][m], costs, spec.trials, member_steps(spec, m))}
    return {"tuning_scenes": spec.tuning_scenes, "members": members}


def _trial_spec(spec: BenchmarkSpec, out: Path, member: str, trial: int) -> CampaignSpec:
    """The campaign a trial is scored on: per scene, the trial's; under transfer, its held-out one."""
    if spec.protocol == "transfer":
        return held_out_campaign_spec(spec, out, member, trial)
    return campaign_spec(spec, member, trial)


def _run_jobs(jobs: Sequence[tuple[CampaignSpec, Path]], out: Path, desc: str, workers: int, executor: Any,
              parallel: str, progress: bool) -> None:
    """Every (campaign, folder) not yet finished (a kept one must be the campaign asked for: an edited one is
    refused, named), campaigns side by side or one at a time (``parallel_mode``)."""
    bar = tqdm(total=len(jobs), desc=desc, unit="campaign", disable=not progress)
    for campaign, folder in jobs:
        if finished(folder):
            check_finished_campaign(campaign, folder)
    todo = [(c, f) for c, f in jobs if not finished(f)]
    bar.update(len(jobs) - len(todo))
    if parallel_mode(parallel, workers, executor, len(todo)) == "campaigns":
        from genesis_rl.benchmark.parallel import run_side_by_side
        from genesis_rl.benchmark.ray_campaigns import run_campaigns_on_ray

        try:
            if executor is not None:
                run_campaigns_on_ray(todo, executor, on_done=lambda folder: bar.update())
            else:
                run_side_by_side(todo, workers, on_done=lambda folder: bar.update())
        except KeyboardInterrupt as err:
            kept = ("a campaign an actor was running starts again (its episodes were staged on the actor)"
                    if executor is not None else "a half-run one its finished episodes")
            set_resume_hint(err, f"the finished campaigns in '{out}' are kept, and {kept}; the same command "
                                 "with --resume runs the rest")
            raise
    else:
        try:
            for campaign, folder in todo:
                bar.set_postfix_str(str(folder.relative_to(out / "campaigns")))
                run_campaign_once(campaign, folder, workers=workers, executor=executor)
                bar.update()
        except KeyboardInterrupt as err:  # the trial's own hint ("run the command again") is the campaign's;
            # the benchmark folder stays, and only --resume continues it
            set_resume_hint(err, f"the finished campaigns in '{out}' are kept, and a half-run one its finished "
                                 "episodes; the same command with --resume runs the rest")
            raise
    bar.close()


def member_trials(spec: BenchmarkSpec, out: Path, member: str) -> Sequence[Path]:
    """The campaign folders of ``member``'s trials, in trial order."""
    return [campaign_folder(out, member, t) for t in range(spec.trials)]
