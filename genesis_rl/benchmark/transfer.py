"""The transfer protocol: tuned once on some scenes, judged on scenes nobody tuned on.

The per-scene protocol lets a search spend its budget on the very scene it is scored on. The paper's claim is
another one: an adversary trained once produces failures on scenes it has never seen. So, per member and
trial, the scenes are split in two disjoint sets (``CampaignSpec.exclude``):

- *tuning scenes*: every search (``SEARCHES``) runs as in the per-scene protocol, its budget on each scene,
  and every episode is recorded (``records = "all"``);
- *held-out scenes* (the per-scene protocol's own trial scenes, so the two protocols are scored on the same
  scenes): every adversary plays **one** episode a scene with no further search. A search replays the best
  schedule it found on the tuning scenes, start included (``best_schedule``; ``adversaries.replay``); a step
  policy (sunny, random, constant, a scripted watcher) and a trained agent simply play.

The held-out campaign is scored, re-run on fresh world seeds and ranked as any trial's. What each adversary
cost is counted in simulator steps, training and tuning included (``transfer_costs``), and for each trained
agent and search the number of held-out scenes after which the agent's training has paid for itself
(``break_even_scenes``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from genesis_rl.core.errors import UserInputError

if TYPE_CHECKING:  # the command's parser reads this module's defaults: the campaign machinery loads when run
    from genesis_rl.adversaries.replay import Schedule
    from genesis_rl.benchmark.metrics import Trial
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.sut.zoo.trigger import TriggerRegion

#: the adversaries that search a scene (spend episodes on it) and so are tuned, then replayed, under transfer
SEARCHES = ("random_search", "corner_search", "cmaes", "cem", "mcts", "goexplore", "verifai_ce", "verifai_mab",
            "verifai_bo")
#: tuning scenes per trial unless the benchmark says otherwise
DEFAULT_TUNING_SCENES = 4


def tuned(policies: Sequence[str]) -> tuple[str, ...]:
    """The policies that are tuned on the tuning scenes (the searches among ``policies``), in their order."""
    return tuple(p for p in policies if p in SEARCHES)


def held_out_scenes(held_out: CampaignSpec) -> tuple[int, ...]:
    """The scene indices the held-out campaign plays (what ``prepare_campaign`` will draw), from its catalog's
    size: generated once a process (``sim.lite.scenes`` keeps it)."""
    from genesis_rl.campaigns.campaign_spec import pick_scenes
    from genesis_rl.sim.backends import catalog_or_generate
    from genesis_rl.sim.lite.scenes import DEFAULT_COUNTS

    catalog = catalog_or_generate(held_out.catalog, held_out.map, DEFAULT_COUNTS.get(held_out.map, 1),
                                  held_out.catalog_seed, traffic=held_out.traffic)
    return tuple(s for s, _ in pick_scenes(len(catalog.scenes), held_out.scenes, held_out.seed))


def tuning_spec(held_out: CampaignSpec, tuning_scenes: int, exclude: tuple[int, ...]) -> CampaignSpec:
    """The tuning campaign of a trial: its searches on ``tuning_scenes`` scenes none of which is held out, every
    episode recorded (a schedule is read back from its record's start)."""
    policies = tuned(held_out.policies)
    if not policies:
        raise UserInputError(f"benchmark protocol transfer: none of the policies {list(held_out.policies)} "
                             f"searches; allowed searches: {', '.join(SEARCHES)}")
    return replace(held_out, policies=policies, scenes=tuning_scenes, exclude=tuple(sorted(exclude)), records="all")


def score_key(trial: Trial, control: bool, episode_return: float, scene: int) -> tuple[bool, bool, float, int]:
    """How a tuned schedule is chosen among a search's tuning episodes: a hit (a triggered failure; on a
    control any in-ODD failure) first, then any in-ODD failure, then the highest return (the search's own
    objective), then the lowest scene index (a tie is decided the same way every time)."""
    return trial.hit(control), trial.failure_at is not None, episode_return, -scene


def best_schedule(folder: Path, policy: str, region: TriggerRegion) -> tuple[Schedule, dict[str, Any]]:
    """The schedule ``policy`` replays on held-out scenes: its best reported tuning episode's start and knobs
    (``score_key``), with what chose it (scene, hit, failure step, return)."""
    from genesis_rl.adversaries.base import in_odd_failure_at
    from genesis_rl.adversaries.replay import Schedule
    from genesis_rl.benchmark.metrics import Trial
    from genesis_rl.campaigns.campaign_files import read_step_records
    from genesis_rl.campaigns.loaded import load_typed_campaign
    from genesis_rl.campaigns.records import load_record
    from genesis_rl.world.knobs import Weather

    campaign = load_typed_campaign(Path(folder))
    rows = list(campaign.episodes.get(policy) or ())
    if not rows:
        raise UserInputError(f"tuning campaign '{folder}' holds no episode of '{policy}'; run it again "
                             "(delete the folder, or --resume)")
    best: tuple[tuple[bool, bool, float, int], Any, list[Any], Trial] | None = None
    for row in rows:
        records = read_step_records(campaign.folder.steps(policy, row.scene), row.steps)
        trial = Trial(row.scene, len(records), region.reached(records), in_odd_failure_at(records))
        key = score_key(trial, region.empty, row.episode_return, row.scene)
        if best is None or key > best[0]:
            best = (key, row, records, trial)
    assert best is not None
    key, row, records, trial = best
    if not row.record:
        raise UserInputError(f"tuning campaign '{folder}': the episode of '{policy}' on scene {row.scene} has no "
                             "record (a tuning campaign records every episode); run it again")
    start = load_record(campaign.folder.root / row.record).get("start_weather")
    schedule = Schedule.of_episode(None if start is None else Weather.from_recorded(start), [r.knobs for r in records])
    return schedule, {"scene": row.scene, "hit": key[0], "failure_at": trial.failure_at,
                      "return": round(row.episode_return, 3), "tuning_steps": sum(int(r["sim_steps"]) for r in rows)}


def held_out_spec(held_out: CampaignSpec, schedules: Mapping[str, Schedule]) -> CampaignSpec:
    """The held-out campaign: every policy plays once a scene, each tuned search replaying its schedule."""
    from genesis_rl.adversaries.replay import OPTION

    options = {**held_out.options, OPTION: {p: s.to_json() for p, s in sorted(schedules.items())}}
    options.pop("search_budget", None)  # nothing searches here; the budget was spent on the tuning scenes
    return replace(held_out, options=options)


def campaign_steps(folder: Path) -> dict[str, int]:
    """Per policy, the simulator steps its episodes in the campaign ``folder`` cost (a search's every candidate)."""
    from genesis_rl.campaigns.loaded import load_typed_campaign

    campaign = load_typed_campaign(Path(folder))
    return {p: sum(int(r["sim_steps"]) for r in rows) for p, rows in campaign.episodes.items()}


def seen_in_training(run: str, held_out: CampaignSpec, scenes: Sequence[int]) -> int | None:
    """How many of the held-out ``scenes`` the trained agent of ``run`` trained on: the scenes its env generated
    (``env.scenes`` of ``env.map`` from ``env.catalog_seed``, the mixed traffic a training env generates) are
    the campaign's own catalog's first ones when map, seed and traffic agree; 0 when they do not; None when
    the run trained on a catalog file (its scenes are not compared)."""
    from genesis_rl.campaigns.campaign_spec import env_settings_for
    from genesis_rl.env.genesis_env import EnvConfig

    env = env_settings_for(run, None, None)
    if env.get("catalog"):
        return None
    defaults = EnvConfig()
    same = (env.get("map", defaults.map) == held_out.map and held_out.catalog is None
            and int(env.get("catalog_seed", defaults.catalog_seed)) == held_out.catalog_seed
            and held_out.traffic == "mixed")
    count = int(env.get("scenes", defaults.scenes))
    return sum(1 for s in scenes if s < count) if same else 0


def transfer_costs(tuning: Sequence[Mapping[str, int]], held_out: Sequence[Mapping[str, int]],
                   training: Mapping[str, int | None]) -> dict[str, dict[str, int | None]]:
    """Per policy, summed over the trials: the steps spent tuning, training (a trained agent; None: unknown, a
    loose agent file), on the held-out scenes, and in all. A trained agent is trained once for every trial,
    so its training counts once."""
    out: dict[str, dict[str, int | None]] = {}
    for policy in sorted({p for d in held_out for p in d}):
        tune = sum(d.get(policy, 0) for d in tuning)
        play = sum(d.get(policy, 0) for d in held_out)
        train = training.get(policy, 0)
        out[policy] = {"tuning_steps": tune, "training_steps": train, "held_out_steps": play,
                       "total_steps": None if train is None else tune + train + play}
    return out


def break_even_scenes(agent_fixed: float, agent_rate: float, search_fixed: float, search_rate: float,
                      episode_steps: float) -> float | None:
    """After how many held-out scenes the agent's steps per confirmed failure drop to the search's.

    Each pays a fixed cost once (the agent its training, the search its tuning) and one episode a held-out
    scene, so over n scenes its steps per confirmed failure are (fixed + n E) / (n rate). The agent breaks even
    at n = (T_a r_s - T_s r_a) / (E (r_a - r_s)). Returns 0.0 when the agent is never dearer, None when it
    never breaks even (it confirms fewer failures a scene, or as many at a higher fixed cost)."""
    if agent_rate <= 0.0:
        return None
    if search_rate <= 0.0:
        return 0.0  # the search confirms nothing: any failure the agent confirms is cheaper
    if agent_rate == search_rate:
        return 0.0 if agent_fixed <= search_fixed else None
    if agent_rate < search_rate:
        return None  # dearer a failure on every scene from some n on: its training never pays for itself
    return max(0.0, (agent_fixed * search_rate - search_fixed * agent_rate) /
               (episode_steps * (agent_rate - search_rate)))


def break_even_table(cells: Mapping[str, Mapping[str, Any]], costs: Mapping[str, Mapping[str, int | None]],
                     trials: int, episode_steps: int) -> dict[str, dict[str, float | None]]:
    """For each trained agent (``agent:...`` cells) and each tuned search: ``break_even_scenes`` from their
    confirmed rates on the held-out scenes and their fixed costs: the agent's training (once), the search's
    tuning of one trial (``trials`` of them summed in ``costs``); an agent whose training steps are unknown is
    left out."""
    out: dict[str, dict[str, float | None]] = {}
    for agent, cell in cells.items():
        if not agent.startswith("agent:") or costs.get(agent, {}).get("training_steps") is None:
            continue
        row: dict[str, float | None] = {}
        for search in (p for p in cells if p in SEARCHES):
            n = break_even_scenes(float(costs[agent]["training_steps"] or 0), float(cell["confirmed_rate"] or 0.0),
                                  float(costs.get(search, {}).get("tuning_steps") or 0) / trials,
                                  float(cells[search]["confirmed_rate"] or 0.0), float(episode_steps))
            row[search] = None if n is None else round(n, 1)
        out[agent] = row
    return out
