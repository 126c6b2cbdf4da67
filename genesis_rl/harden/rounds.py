"""The hardening loop (``genesis-rl harden``): attack -> retrain -> re-test, round after round.

Round ``r`` starts from the weights round ``r - 1`` accepted (round 1: the campaign's own system):

1. **attack**: round 1's failures are the given campaign's; a later round re-runs that campaign's spec (its
   adversaries, env, steps) against the current weights on scenes picked by another seed (``seed + r - 1``);
2. **data**: the in-ODD failures of the attack (collisions that began inside the ODD or on its boundary), their
   kept frames up to the impact, exported with the simulator's labels (``genesis-rl export``'s YOLO layout);
3. **retrain**: the hook (built-in: fine-tune the detector on every round's failure frames so far mixed with its
   own training data) writes new weights;
4. **re-test**: the same adversaries on held-out scenes (another catalog, the same scenes and episode seeds every
   round, so rounds compare paired) give the in-ODD failure rate; the clear-day detector evaluation gives
   precision and recall, and a round that lowers either by more than the tolerance (the seesaw) is rejected:
   the next round starts from the weights before it.

After the last round a final attack measures what a re-run adversary finds against the hardened system. Round 0
is the baseline: the held-out test and the clear-day evaluation of the weights before any round.

``--resume`` reuses what is on disk: a kept round (``round.json``, the weights it made, its failure export and
near misses), every stage's campaign, the rendered original data (``.npz``), the final agent and the estimates.
Each is pinned in the folder's ``pins.json`` when written (``core/files/pins.py``) and checked before it is
reused, as are the attack campaign and the starting weights: an edited one is refused, named.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write_json
from genesis_rl.core.files.pins import Pins, plain
from genesis_rl.core.parsing import read_json
from genesis_rl.harden.loop import relative_to  # round.json stores paths inside the harden folder relative to it
from genesis_rl.harden.near_miss import IN_ODD, near_misses  # IN_ODD: failures and near misses alike

SCHEMA = "genesis-rl/harden"
#: what a setting added after 0.22.0 meant for a hardening whose harden.json predates it (``--resume``)
LEGACY: dict[str, Any] = {"retest_scenes": 0, "near_miss_ttc": 0}


@dataclass(frozen=True)
class HardenSpec:
    """Everything that decides a hardening's results (``workers`` does not)."""

    campaign: str  # the attack campaign: round 1's failures, and the spec later rounds re-run
    rounds: int = 3
    test_scenes: int = 20  # held-out scenes of the re-test
    #: scenes of the later rounds' attacks and the final one (None: the campaign's own count); a hardened system
    #: fails rarely, so finding what is left takes a bigger attack
    attack_scenes: int | None = None
    test_catalog_seed: int | None = None  # the held-out catalog (default: the attack catalog's seed + 1)
    #: a catalog file of held-out scenes instead of a generated one (a CARLA town's, or fewer scenes)
    test_catalog: str | None = None
    seed: int = 0  # the retraining's draws
    retrain: str = "builtin"  # the hook: builtin (fine-tune a genesis-rl detector) or package.module:function
    finetune: dict[str, Any] = field(default_factory=dict)  # the hook's options (FinetuneConfig fields)
    clear_frames: int = 200  # clear-day evaluation frames on the campaign's map
    tolerance: float = 0.01  # the largest clear-day precision or recall drop a round may cause
    #: a train config (TOML): an agent trained by it against the final weights re-attacks them (the re-trained
    #: adversary); None: only the campaign's own adversaries re-attack
    adversary: str | None = None
    #: a zoo member whose system and ODD the campaign ran: its in-ODD failure rate under natural conditions is
    #: estimated (crude Monte Carlo, ``estimate_episodes`` episodes) before the rounds and for the final weights
    member: str | None = None
    estimate_episodes: int = 0
    #: after the rounds, the weights before any round and every round's are re-tested on this many held-out scenes
    #: (the same catalog, scenes and episode seeds for all): the in-loop re-test is small, and a falling rate needs
    #: more episodes to be told apart round from round (0: none)
    retest_scenes: int = 0
    #: near misses join the data: collision-free episodes whose time to collision with the lead fell to this many
    #: seconds or below inside the ODD, with their frames up to the closest approach (0: failures only)
    near_miss_ttc: float = 1.5

    def __post_init__(self) -> None:
        if self.attack_scenes is not None and (not isinstance(self.attack_scenes, int) or self.attack_scenes < 1):
            raise UserInputError(f"harden attack_scenes = {self.attack_scenes!r}; allowed: an integer >= 1")
        for name, low in (("rounds", 1), ("test_scenes", 1), ("clear_frames", 1)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise UserInputError(f"harden {name} = {value!r}; allowed: an integer >= {low}")
        if not isinstance(self.retest_scenes, int) or isinstance(self.retest_scenes, bool) or self.retest_scenes < 0:
            raise UserInputError(f"harden retest_scenes = {self.retest_scenes!r}; allowed: an integer >= 0")
        if isinstance(self.near_miss_ttc, bool) or not (isinstance(self.near_miss_ttc, (int, float))
                                                        and 0 <= self.near_miss_ttc <= 10):
            raise UserInputError(f"harden near_miss_ttc = {self.near_miss_ttc!r}; allowed: seconds in [0, 10] (0: "
                                 "no near misses)")
        if not isinstance(self.estimate_episodes, int) or self.estimate_episodes < 0:
            raise UserInputError(f"harden estimate_episodes = {self.estimate_episodes!r}; allowed: an integer >= 0")
        if self.estimate_episodes and self.member is None:
            raise UserInputError("--estimate-episodes needs --member (the zoo member whose system and ODD the "
                                 "campaign ran: its natural conditions define the rate)")
        if not (isinstance(self.tolerance, (int, float)) and 0 <= self.tolerance < 1):
            raise UserInputError(f"harden tolerance = {self.tolerance!r}; allowed: a number in [0, 1)")
        if self.retrain == "builtin":
            from genesis_rl.harden.retrain import check_options

            check_options(self.finetune)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ------------------------------------------------------------------------------------------- campaigns
def _with_weights(env: Mapping[str, Any], weights: Path | None) -> dict[str, Any]:
    env = dict(env)
    if weights is not None:
        env["system_kwargs"] = {**env.get("system_kwargs", {}), "weights": str(Path(weights).resolve())}
    return env


def start_weights(env: Mapping[str, Any]) -> Path:
    """The weights the campaign's system ran with (the shipped detector's when it names none)."""
    given = env.get("system_kwargs", {}).get("weights")
    if given:
        return Path(given)
    if env.get("system", "builtin") in ("builtin", "latency", "adaptive"):
        from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS

        return DEFAULT_WEIGHTS
    if env.get("system") == "coco":  # the model store's darknet folder
        from genesis_rl.sut.perception.model_store import find_model

        return find_model("coco")["yolov3-tiny.weights"].parent
    raise UserInputError(f"campaign system '{env.get('system')}' names no weights (system_kwargs.weights); "
                         "harden retrains a system's weights, so run the campaign with --weights")


def attack_spec(base: Any, r: int, weights: Path | None, scenes: int | None = None) -> Any:
    """Round ``r``'s attack: the campaign's spec against ``weights`` on the ``scenes`` (default: the campaign's
    count) that seed ``base.seed + r - 1`` picks."""
    return dataclasses.replace(base, seed=base.seed + r - 1, scenes=scenes or base.scenes,
                               env=_with_weights(base.env, weights))


def test_spec(base: Any, spec: HardenSpec, weights: Path | None) -> Any:
    """The held-out re-test: the campaign's adversaries on ``test_scenes`` scenes of another catalog (the
    ``test_catalog`` file, else a generated one)."""
    if spec.test_catalog is not None:
        return dataclasses.replace(base, catalog=spec.test_catalog, scenes=spec.test_scenes,
                                   env=_with_weights(base.env, weights))
    seed = test_catalog_seed(base, spec)
    return dataclasses.replace(base, catalog=None, catalog_seed=seed, scenes=spec.test_scenes,
                               env=_with_weights(base.env, weights))


def check_test_catalog(base: Any, spec: HardenSpec) -> None:
    """A held-out catalog file must hold the campaign's map, enough scenes, and not be the attack's own."""
    if spec.test_catalog is None:
        test_catalog_seed(base, spec)
        return
    from genesis_rl.campaigns.campaign_spec import campaign_map
    from genesis_rl.world.scenes.catalog import read_catalog

    if spec.test_catalog_seed is not None:
        raise UserInputError("--test-catalog and --test-catalog-seed both name the held-out scenes; pass one")
    if base.traffic != "mixed":
        raise UserInputError(f"--test-catalog: the campaign's traffic is '{base.traffic}', generated on the fly; "
                             "its held-out scenes come from --test-catalog-seed")
    campaign_map(base.map, spec.test_catalog)  # refuses another map's catalog, naming both
    if base.catalog and Path(base.catalog).resolve() == Path(spec.test_catalog).resolve():
        raise UserInputError(f"--test-catalog '{spec.test_catalog}' is the attack campaign's own catalog; held-out "
                             "scenes need another")
    n = len(read_catalog(spec.test_catalog).scenes)
    for flag, count in (("--test-scenes", spec.test_scenes), ("--retest-scenes", spec.retest_scenes)):
        if count > n:
            raise UserInputError(f"{flag} {count}: --test-catalog '{spec.test_catalog}' holds {n} scenes")


def test_catalog_seed(base: Any, spec: HardenSpec) -> int:
    seed = spec.test_catalog_seed if spec.test_catalog_seed is not None else base.catalog_seed + 1
    if base.catalog is None and seed == base.catalog_seed:
        raise UserInputError(f"--test-catalog-seed {seed} is the attack campaign's own catalog seed; held-out "
                             "scenes need another")
    return int(seed)


def _run(campaign_spec: Any, folder: Path, workers: int, progress: bool, pins: Pins | None = None) -> None:
    """Play ``campaign_spec`` into ``folder``, or resume it there. A campaign of another spec in ``folder`` is
    replaced: a resume that added rounds moves the final attack to other weights and seed. With ``pins`` (the
    harden folder's), a campaign kept is first checked against the files and the spec it was pinned with."""
    from genesis_rl.campaigns.campaign import run_campaign
    from genesis_rl.campaigns.campaign_files import read_campaign_meta
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.core.files.io_utils import remove_tree

    camp = CampaignFolder(folder)
    wanted = campaign_spec.to_json()
    pinned = False
    if camp.meta.is_file():
        if pins is not None:  # a finished stage: the files it was pinned with (an edit is refused, named)
            pinned = pins.check(folder, CampaignFolder.holds_results)
        recorded = CampaignSpec.from_json(read_campaign_meta(folder)["spec"]).to_json()
        started = pins.spec(folder) if pins is not None else None
        if started is not None and plain(recorded) != started:
            diff = sorted(k for k in set(started) | set(recorded) if plain(recorded).get(k) != started.get(k))
            raise UserInputError(f"--resume: '{camp.meta}' holds other settings than harden started this campaign "
                                 f"with ({', '.join(diff)}): it was edited or belongs to another run; start again "
                                 "with --force")
        if recorded != wanted:
            if pins is not None:
                pins.forget(folder)
            remove_tree(folder)
            pinned = False
    if not camp.summary.is_file():
        if pins is not None:
            pins.note_spec(folder, wanted)
        run_campaign(campaign_spec, folder, workers=workers, resume=camp.meta.is_file(), progress=progress)
        if pins is not None:
            pins.record(folder, CampaignFolder.holds_results, spec=wanted)
    elif pins is not None and not pinned:
        pins.record(folder, CampaignFolder.holds_results, spec=wanted)  # a folder of before the pins


def in_odd_failures(folder: Path) -> dict[str, Any]:
    """The campaign's in-ODD failures: the episodes, their count and rate (exact 95 % CI) over every episode of
    every policy, the distinct ones, and the (policy, scene) -> impact step of each."""
    from genesis_rl.campaigns.loaded import load_typed_campaign
    from genesis_rl.core.stats import clopper_pearson
    from genesis_rl.labels.distinct import clusters, failure_of

    campaign = load_typed_campaign(folder)
    rows = campaign.episodes
    episodes = campaign.episode_count()
    failures = [failure_of(r, p) for p, eps in rows.items() for r in eps
                if r.failure and r.failure.get("odd_status") in IN_ODD]
    if episodes and not any("odd" in r for eps in rows.values() for r in eps):
        raise UserInputError(f"campaign '{folder}' has no ODD labels (run it with an ODD, e.g. a zoo member's "
                             "config): harden takes the in-ODD failures")
    impacts = {(f["policy"], int(f["scene"])): int(f["step"]) for f in failures}
    return {"folder": str(folder), "episodes": episodes, "in_odd_failures": len(failures),
            "rate": clopper_pearson(len(failures), episodes) if episodes else None,
            "distinct": len(clusters(failures)), "impacts": impacts,
            "by_policy": {p: sum(1 for f in failures if f["policy"] == p) for p in rows}}


def _public(result: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in result.items() if k != "impacts"}


# -------------------------------------------------------------------------------------------- clear day
def clear_day(system: str, system_kwargs: Mapping[str, Any], map_name: str, frames: int,
              progress: bool) -> dict[str, Any] | None:
    """The system's detector on clear-day frames of its map (``detector eval``'s protocol and held-out scenes);
    None when the system exposes no ``detector``."""
    from genesis_rl.sut.perception.evaluate import evaluate_detector
    from genesis_rl.sut.system.protocol import load_system

    detector = getattr(load_system(system, **dict(system_kwargs)), "detector", None)
    if detector is None or not callable(getattr(detector, "detect_batch", None)):
        return None
    (row,) = evaluate_detector(detector, (map_name,), ("clear",), frames, progress=progress)
    return row


def seesaw(before: Mapping[str, Any] | None, after: Mapping[str, Any] | None, tolerance: float) -> dict[str, Any]:
    """Whether a round kept clear-day precision and recall within ``tolerance`` of the weights before any round."""
    if before is None or after is None:
        return {"checked": False, "ok": True, "why": "the system exposes no detector to evaluate"}
    drops = {k: round(float(before[k] or 0) - float(after[k] or 0), 4) for k in ("precision", "recall")}
    bad = [k for k, d in drops.items() if d > tolerance]
    return {"checked": True, "ok": not bad, "drop": drops, "tolerance": tolerance,
            "why": f"clear-day {' and '.join(bad)} fell by more than {tolerance}" if bad else ""}


# ------------------------------------------------------------------------------------------------ loop
def run_harden(spec: HardenSpec, out: Path, *, workers: int = 1, force: bool = False, resume: bool = False,
               progress: bool = True) -> dict[str, Any]:
    """Play the rounds not yet on disk; write ``harden.json``, ``harden.png`` and ``harden.html``; the result."""
    from genesis_rl import __version__
    from genesis_rl.campaigns.campaign_files import read_campaign_meta
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.core.files.hashing import file_sha256
    from genesis_rl.harden.retrain import load_hook

    out = Path(out)
    campaign = Path(spec.campaign)
    output_folder.check_folder_inputs(out, [campaign, spec.adversary, spec.test_catalog])
    base = CampaignSpec.from_json(read_campaign_meta(campaign)["spec"])
    hook = load_hook(spec.retrain)  # a bad name is refused before anything runs
    if spec.adversary is not None:
        from genesis_rl.training.config import load_run_config

        if not Path(spec.adversary).is_file():
            raise UserInputError(f"--adversary '{spec.adversary}' is not a file (a train config, as genesis-rl "
                                 "train --config takes)")
        load_run_config(spec.adversary)  # a bad config is refused before anything runs
    check_test_catalog(base, spec)
    if spec.member is not None:
        check_member(spec.member, base)
    weights0 = start_weights(base.env)
    system, kwargs0 = base.env.get("system", "builtin"), dict(base.env.get("system_kwargs", {}))
    if spec.retrain == "builtin":
        from genesis_rl.harden.retrain import check_options

        check_options(spec.finetune, system)  # a setting of the other kind's fine-tune, before anything runs
    if resume and not (out / "harden.json").exists():
        raise UserInputError(f"--resume: '{out}' holds no harden.json; start it without --resume")
    with output_folder.claim(out, "harden", force, resume=resume, inputs=[campaign]):
        if resume:
            # what runs after the rounds done, and the attack size of rounds still to come (each round records its own)
            output_folder.check_same_settings(
                "harden", out, output_folder.recorded_spec(out / "harden.json", "harden"), spec.to_json(),
                may_change=("rounds", "adversary", "member", "estimate_episodes", "attack_scenes", "retest_scenes"),
                defaults=LEGACY)
            pins = Pins(out)
            _check_started_with(out, pins, campaign, weights0, _sha(weights0, file_sha256))
        else:
            output_folder.replace(out, "harden")
            pins = Pins.start(out)
            from genesis_rl.campaigns.summary import load_campaign

            load_campaign(campaign)  # rows of an older labeller are relabelled (rewritten) before they are pinned
            pins.record(campaign, CampaignFolder.holds_results)
        head = {"schema": SCHEMA, "version": __version__, "spec": spec.to_json(), "system": system,
                "map": base.map, "base_weights": str(weights0), "base_weights_sha256": _sha(weights0, file_sha256)}
        atomic_write_json(out / "harden.json", {**head, "done": False}, indent=1)

        baseline = _baseline(spec, base, out / "round_0", system, kwargs0, weights0, workers, progress, pins)
        rounds: list[dict[str, Any]] = []
        weights = weights0
        failure_exports: list[Path] = []
        stopped = ""
        for r in range(1, spec.rounds + 1):
            result = _round(spec, base, out, r, system, kwargs0, weights, failure_exports, baseline, hook,
                            workers, progress, pins)
            rounds.append(result)
            atomic_write_json(out / "harden.json", {**head, "done": False, "baseline": baseline, "rounds": rounds},
                              indent=1)
            if result["status"] == "no failure":
                stopped = f"round {r}'s attack found no in-ODD failure"
                break
            if result["status"] == "accepted":
                weights = inside(out, result["weights"])
        final = None
        if not stopped:
            folder = out / "final_attack"
            _run(attack_spec(base, spec.rounds + 1, weights, spec.attack_scenes), folder, workers, progress, pins)
            final = {**_public(in_odd_failures(folder)), "weights": str(weights)}
        retrained = None
        if spec.adversary:  # also when the same adversary found nothing more: a re-trained one may
            retrained = _retrained_attack(spec.adversary, spec, base, out, weights, workers, progress, pins)
        estimates = None
        if spec.estimate_episodes:
            assert spec.member is not None  # HardenSpec checks it
            estimates = {"before": _estimate(spec, spec.member, weights0, out / "round_0" / "estimate", workers,
                                             progress, pins),
                         "after": _estimate(spec, spec.member, weights, out / "final_estimate", workers, progress,
                                            pins)}
        retest = _retest(spec, base, out, baseline, rounds, workers, progress, pins) if spec.retest_scenes else None
        result = {**head, "done": True, "baseline": baseline, "rounds": rounds, "final_attack": final,
                  "retrained_attack": retrained, "estimates": estimates, "retest": retest,
                  "stopped": stopped, "final_weights": str(weights),
                  "final_weights_sha256": _sha(weights, file_sha256)}
        atomic_write_json(out / "harden.json", result, indent=1)
        from genesis_rl.harden.page import write_page

        write_page(out, result)
        return result


def _check_started_with(out: Path, pins: Pins, campaign: Path, weights0: Path, sha_now: str | None) -> None:
    """A resumed hardening starts from what it began with: the system's weights (harden.json pins their hash)
    and the attack campaign whose failures and spec every round reads (pins.json)."""
    pinned = read_json(out / "harden.json", f"harden '{out}': harden.json").get("base_weights_sha256")
    if isinstance(pinned, str) and pinned != sha_now:
        raise UserInputError(f"--resume: the weights '{weights0}' changed since the hardening in '{out}' began "
                             f"(harden.json pins sha256 {pinned[:12]}, found {(sha_now or 'none')[:12]}): every "
                             "round starts from them; restore them, or start again with --force")
    pins.check_or_record(campaign, CampaignFolder.holds_results)


def check_member(name: str, base: Any) -> None:
    """Refuse a member whose system, map or ODD is not the campaign's (its rate would be of another system)."""
    from genesis_rl.sut.zoo.members import zoo_member

    m = zoo_member(name)
    env = base.env
    theirs: dict[str, Any] = {"system": m.system, "map": m.map, "odd": Path(m.odd_path).resolve()}
    ours: dict[str, Any] = {"system": env.get("system", "builtin"), "map": base.map,
                            "odd": Path(env["odd"]).resolve() if env.get("odd") else None}
    if ours["odd"] is not None and ours["odd"].is_file() and theirs["odd"].is_file() \
            and ours["odd"].read_bytes() == theirs["odd"].read_bytes():
        ours["odd"] = theirs["odd"]  # the same ODD from another checkout (its text is what counts)
    for key, value in theirs.items():
        if ours[key] != value:
            raise UserInputError(f"--member {name}: its {key} is {value}, the campaign's {ours[key]}; give the member "
                                 "whose system and ODD the campaign ran")


#: the files of an estimate folder that a kept estimate is pinned by
ESTIMATE_FILES = ("estimate.json", "episodes.csv", "catalog.json")


def _estimate(spec: HardenSpec, member: str, weights: Path, folder: Path, workers: int,
              progress: bool, pins: Pins | None = None) -> dict[str, Any]:
    """The member's in-ODD failure rate under natural conditions (crude Monte Carlo) with ``weights``."""
    from genesis_rl.estimation.run import EstimateSpec, run_estimate

    est = EstimateSpec(member=member, method="crude", episodes=spec.estimate_episodes, seed=spec.seed,
                       stages=1, weights=str(Path(weights).resolve()))
    kept = ESTIMATE_FILES.__contains__
    if (folder / "estimate.json").is_file():
        pinned = pins is not None and pins.check(folder, kept)
        data = read_json(folder / "estimate.json", f"'{folder}'")
        if data.get("spec", {}).get("weights") != est.weights:  # other weights (a resume that added rounds)
            from genesis_rl.core.files.io_utils import remove_tree

            if pins is not None:
                pins.forget(folder)
            remove_tree(folder)
        elif data.get("done") and data.get("spec", {}).get("episodes") == spec.estimate_episodes:
            if pins is not None and not pinned:
                pins.record(folder, kept)  # an estimate of before the pins: as found
            return {"folder": str(folder), **data["estimate"]}
    result = run_estimate(est, folder, workers=workers, resume=(folder / "estimate.json").is_file(), progress=progress)
    if pins is not None:
        pins.record(folder, kept)
    return {"folder": str(folder), **result["estimate"]}


def _trained_against(run: Path) -> str | None:
    """The weights a final agent was trained against (its config's system_kwargs.weights)."""
    from genesis_rl.core.config import read_toml

    if not (run / "config.toml").is_file():
        return None
    return read_toml(run / "config.toml").get("env", {}).get("system_kwargs", {}).get("weights")


#: the files of the final agent's run that the re-trained attack plays and a resume keeps
AGENT_FILES = ("agent.zip", "train_result.json")


def _retrained_attack(config: str, spec: HardenSpec, base: Any, out: Path, weights: Path, workers: int,
                      progress: bool, pins: Pins | None = None) -> dict[str, Any]:
    """Train an agent by ``config`` against ``weights`` (seed ``spec.seed``), then let it attack them on
    the final attack's scenes."""
    from genesis_rl.core.config import read_toml
    from genesis_rl.training.config import load_run_config
    from genesis_rl.training.train import train

    run = out / "final_agent"
    kept = AGENT_FILES.__contains__
    pinned = pins is not None and pins.check(run, kept)
    if run.exists() and _trained_against(run) != str(Path(weights).resolve()):
        from genesis_rl.core.files.io_utils import remove_tree

        if pins is not None:
            pins.forget(run)
        remove_tree(run)  # trained against other weights (a resume that added rounds)
        pinned = False
    if not (run / "train_result.json").is_file():
        env = dict(read_toml(config).get("env", {}))
        kwargs = {**env.get("system_kwargs", {}), "weights": str(Path(weights).resolve())}
        cfg = load_run_config(config, {"env": {"system_kwargs": kwargs}, "train": {"seed": spec.seed}})
        train(cfg, run, resume=(run / "run.json").is_file(), progress=progress, inputs=[config])
        if pins is not None:
            pins.record(run, kept)
    elif pins is not None and not pinned:
        pins.record(run, kept)  # a run of before the pins, as found
    folder = out / "retrained_attack"
    _run(dataclasses.replace(attack_spec(base, spec.rounds + 1, weights, spec.attack_scenes), policies=("agent",),
                             agent=str(run / "agent.zip")), folder, workers, progress, pins)
    return {**_public(in_odd_failures(folder)), "agent": str(run), "config": config,
            "weights": str(weights)}


def _retest(spec: HardenSpec, base: Any, out: Path, baseline: Mapping[str, Any], rounds: list[dict[str, Any]],
            workers: int, progress: bool, pins: Pins | None = None) -> dict[str, Any]:
    """Every round's weights (round 0: before any round; rejected rounds too) on ``retest_scenes`` held-out scenes
    of the re-test's catalog, in ``retest_N/round_R/``; each rate's fall from the accepted weights before it."""
    wide = dataclasses.replace(spec, test_scenes=spec.retest_scenes)
    rows: list[dict[str, Any]] = []
    before: dict[str, Any] | None = None
    for rnd in [baseline, *rounds]:
        if rnd["round"] and not rnd.get("weights"):
            continue  # an attack that found nothing made no weights
        weights = None if not rnd["round"] else inside(out, rnd["weights"])
        folder = out / f"retest_{spec.retest_scenes}" / f"round_{rnd['round']}"
        _run(test_spec(base, wide, weights), folder, workers, progress, pins)
        found = _public(in_odd_failures(folder))
        row = {"round": rnd["round"], "status": rnd.get("status", "before"), "folder": relative_to(folder, out),
               **{k: found[k] for k in ("episodes", "in_odd_failures", "rate", "distinct")}}
        if before is not None:
            row["fall"] = fall(before["rate"]["rate"], found["rate"]["rate"])
        rows.append(row)
        if row["status"] in ("before", "accepted"):
            before = row
    return {"scenes": spec.retest_scenes, "rounds": rows}


def fall(before: float, after: float) -> float | None:
    """The relative fall of a rate (0.5: halved; negative: it rose); None when there was nothing to fall from."""
    return None if before <= 0 else round(1.0 - after / before, 4)


def inside(out: Path, stored: str) -> Path:
    """A path ``round.json`` stored: relative ones are the harden folder's (those written before 0.22.0 were the
    working directory's, and still read so when the folder holds no such file)."""
    path = Path(stored)
    if path.is_absolute() or not (Path(out) / path).exists():
        return path
    return Path(out) / path


def _sha(path: Path, file_sha256: Any) -> str | None:
    """A weights file's sha256; of a model folder (coco's darknet), the sha256 of its model files' digests."""
    path = Path(path)
    if path.is_dir():
        import hashlib

        files = sorted(f for f in path.iterdir() if f.suffix in (".cfg", ".weights", ".names", ".pt", ".onnx"))
        return hashlib.sha256("".join(f"{f.name}:{file_sha256(f)}\n" for f in files).encode()).hexdigest()
    return file_sha256(path) if path.is_file() else None


def _kept_round(done: Path, out: Path, pins: Pins | None) -> dict[str, Any] | None:
    """A finished round's ``round.json`` (None: the round is to run), checked against its pin, and the weights
    it made against the hash it recorded: the rounds after it start from them."""
    if not done.is_file():
        return None
    if pins is not None:
        pins.check_or_record(done)
    finished = dict(read_json(done, f"'{done}'"))
    made, pinned = finished.get("weights"), finished.get("weights_sha256")
    if finished.get("round") and isinstance(made, str) and isinstance(pinned, str):
        from genesis_rl.core.files.hashing import file_sha256

        found = _sha(inside(out, made), file_sha256)
        if found != pinned:
            raise UserInputError(f"--resume: the weights '{inside(out, made)}' of round {finished['round']} "
                                 f"{'changed' if found else 'are missing'} since the round made them ('{done}' pins "
                                 f"sha256 {pinned[:12]}, found {(found or 'none')[:12]}); start again with --force")
    return finished


def _finish_round(done: Path, result: dict[str, Any], pins: Pins | None) -> None:
    """Write ``round.json`` and pin it (a round kept by a resume is read from it)."""
    atomic_write_json(done, result, indent=1)
    if pins is not None:
        pins.record(done)


def _baseline(spec: HardenSpec, base: Any, folder: Path, system: str, kwargs0: Mapping[str, Any], weights0: Path,
              workers: int, progress: bool, pins: Pins | None = None) -> dict[str, Any]:
    folder.mkdir(parents=True, exist_ok=True)
    done = folder / "round.json"
    kept = _kept_round(done, folder.parent, pins)
    if kept is not None:
        return kept
    _run(test_spec(base, spec, None), folder / "test", workers, progress, pins)
    clear = clear_day(system, kwargs0, base.map, spec.clear_frames, progress)
    result = {"round": 0, "weights": str(weights0), "test": _public(in_odd_failures(folder / "test")), "clear": clear}
    _finish_round(done, result, pins)
    return result


def _round(spec: HardenSpec, base: Any, out: Path, r: int, system: str, kwargs0: Mapping[str, Any], weights: Path,
           failure_exports: list[Path], baseline: Mapping[str, Any], hook: Any, workers: int,
           progress: bool, pins: Pins | None = None) -> dict[str, Any]:
    from genesis_rl.core.files.hashing import file_sha256
    from genesis_rl.exports.dataset import export_dataset
    from genesis_rl.harden.retrain import RetrainRequest

    folder = out / f"round_{r}"
    folder.mkdir(parents=True, exist_ok=True)
    done = folder / "round.json"
    finished = _kept_round(done, out, pins)
    if finished is not None:
        if finished.get("export"):
            export = inside(out, finished["export"])
            if pins is not None:  # the later rounds retrain on it too
                pins.check_or_record(export)
            failure_exports.append(export)
        return finished
    t0 = time.perf_counter()
    attack = Path(spec.campaign) if r == 1 else folder / "attack"
    if r > 1:
        _run(attack_spec(base, r, weights, spec.attack_scenes), attack, workers, progress, pins)
    found = in_odd_failures(attack)
    result: dict[str, Any] = {"round": r, "start_weights": str(weights), "attack": _public(found)}
    if not found["in_odd_failures"]:
        result.update(status="no failure", export=None)
        _finish_round(done, result, pins)
        return result
    impacts = found["impacts"]
    near = near_misses(attack, spec.near_miss_ttc)
    near_root = folder / "near_misses"
    rendered = _near_miss_frames(attack, near, near_root, weights, base, progress, pins)
    closest = {key: int(near[key]["step"]) for key in near
               if f"{key[0]}_scene_{key[1]:04d}" in rendered["episodes"]}
    export = folder / "failures"
    if pins is not None and (export / "export.json").is_file():
        pins.check_or_record(export)
    if not (export / "export.json").is_file():
        export_dataset(attack, "yolo", export, force=export.exists(),
                       keep=lambda p, s, step: (p, s) in impacts and step <= impacts[(p, s)]
                       or (p, s) in closest and step <= closest[(p, s)],
                       extra_frames=near_root if closest else None)
        if pins is not None:
            pins.record(export)
    failure_exports.append(export)
    exported = read_json(export / "export.json", f"'{export}'")
    result["near_misses"] = {"ttc_s": spec.near_miss_ttc, "found": len(near), "exported": len(closest),
                             "frames": len(list(near_root.glob("frames/*/*/*.jpg"))),
                             "departed": rendered["departed"], "unrecorded": rendered["unrecorded"],
                             "episodes": {f"{p}_scene_{s:04d}": v for (p, s), v in sorted(near.items())}}
    request = RetrainRequest(round=r, system=system, weights=weights, failures=tuple(failure_exports),
                             out=folder / "weights", seed=spec.seed, work=out, options=dict(spec.finetune),
                             progress=progress, map=base.map, system_kwargs=dict(kwargs0))
    new_weights = Path(hook(request))
    if not new_weights.exists():
        raise UserInputError(f"retrain hook '{spec.retrain}' returned '{new_weights}', which does not exist")
    kwargs = {**kwargs0, "weights": str(new_weights.resolve())}
    _run(test_spec(base, spec, new_weights), folder / "test", workers, progress, pins)
    clear = clear_day(system, kwargs, base.map, spec.clear_frames, progress)
    check = seesaw(baseline.get("clear"), clear, spec.tolerance)
    result.update(export=relative_to(export, out), frames=exported.get("images"), labels=exported.get("labels"),
                  weights=relative_to(new_weights, out), weights_sha256=_sha(new_weights, file_sha256),
                  test=_public(in_odd_failures(folder / "test")), clear=clear, seesaw=check,
                  status="accepted" if check["ok"] else "seesaw", seconds=round(time.perf_counter() - t0, 1))
    _finish_round(done, result, pins)
    return result


def _near_miss_frames(attack: Path, near: Mapping[tuple[str, int], Mapping[str, float]], root: Path, weights: Path,
                      base: Any, progress: bool, pins: Pins | None = None) -> dict[str, Any]:
    """The near misses' frames, rendered again into ``root`` (once: ``root/near_misses.json`` marks them done)."""
    from genesis_rl.core.files.io_utils import remove_tree
    from genesis_rl.harden.near_miss import render_frames

    done = root / "near_misses.json"
    if done.is_file():
        if pins is not None:
            pins.check_or_record(root)
        return dict(read_json(done, f"'{done}'"))
    if root.exists():  # an interrupted rendering: its frames may be partial
        if pins is not None:
            pins.forget(root)
        remove_tree(root)
    if not near:
        return {"episodes": [], "departed": [], "unrecorded": []}
    rendered = render_frames(attack, near, root, weights, base.frames_before, base.frame_stride, progress)
    atomic_write_json(done, rendered, indent=1)
    if pins is not None:
        pins.record(root)
    return rendered


def load_harden(folder: Path) -> dict[str, Any]:
    """A finished hardening's ``harden.json``."""
    data = read_json(Path(folder) / "harden.json", f"harden '{folder}'")
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise UserInputError(f"'{folder}/harden.json' is not a genesis-rl harden result")
    return data
