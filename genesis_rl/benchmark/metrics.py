"""The metrics of a falsifier on one zoo member: one campaign folder, per policy, over its episodes (one
episode = one scene = one trial under the campaign's simulator-step budget).

What the fields that measure their tools against ground truth report (ARCH-COMP's falsification rate and
simulations to the first falsification, Magma's reached/triggered canaries and time-to-bug survival curves,
the SBST tool competition's distinct failures), for a driving system inside its ODD:

- an *in-ODD failure* is a collision whose first step is labelled ``inside`` or ``boundary`` of the ODD;
- *falsification rate*: the share of trials with one;
- *reached*: the trial entered the member's trigger region; *triggered*: an in-ODD failure at or after the
  first reached step. Never reached says exploration; reached but not triggered says timing or naturalness;
- *steps to the first in-ODD failure*, censored at the trial's steps when it had none, and their
  Kaplan-Meier curve;
- *distinct in-ODD failures*: the campaign's own clusters (``evaluation.distinct``, over each episode's
  labelled first collision, as the summary counts them);
- on a *control* every in-ODD failure is a false alarm candidate (with its blame and oracle replay, where the
  campaign ran one);
- *avoidable*: failed trials less those whose reported failure is blamed ``unavoidable`` (the careful driver of
  the episode's blame reference collides as well): an unavoidable failure is not the system's. A
  search's earlier candidates are not blamed one by one, so its trial counts as its reported episode says;
- *reproducible*: the reported failure, re-run on fresh world seeds (``benchmark.reproduce``), failed again (and
  triggered again, on a weakness) in at least half of the re-runs;
- *confirmed*, the primary score: the reported episode's in-ODD failure is triggered (on a control: any), avoidable
  and reproducible, all read from that one episode. Raw in-ODD collisions (``failed``, which counts any of a
  search's candidates) stay a secondary figure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from genesis_rl.adversaries.base import in_odd_failure_at
from genesis_rl.benchmark.survival import kaplan_meier, median_time
from genesis_rl.campaigns.campaign_files import read_step_records
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.stats import clopper_pearson
from genesis_rl.labels.distinct import KEY_FIELDS, natural_summary
from genesis_rl.sut.zoo.members import ZooMember, zoo_member
from genesis_rl.sut.zoo.trigger import TriggerRegion
from genesis_rl.world.odd.domain import IN_ODD, load_odd
from genesis_rl.world.step_record import StepRecord


@dataclass(frozen=True)
class Trial:
    """One scene against the member: the simulator steps it spent, when the reported episode first entered the
    trigger region and when it first failed inside the ODD (step indices; None: never). A search spends several
    episodes on a scene: ``first_failure_steps`` counts the steps of every candidate it played before its
    first in-ODD failure, up to and including that failure (None: no candidate failed, or a single episode)."""

    scene: int
    steps: int
    reached_at: int | None
    failure_at: int | None
    first_failure_steps: int | None = None
    #: the reported episode's in-ODD failure is blamed ``unavoidable``: the careful driver collides as well
    unavoidable: bool = False
    #: re-runs of the reported failure on fresh world seeds, and how many of them reproduced it (0, 0: not re-run)
    reruns: int = 0
    reproduced: int = 0

    @property
    def failed(self) -> bool:
        return self.failure_at is not None or self.first_failure_steps is not None

    @property
    def avoidable(self) -> bool:
        """Failed, and not a failure the careful driver could not avoid either."""
        return self.failed and not self.unavoidable

    @property
    def reached(self) -> bool:
        return self.reached_at is not None

    @property
    def reproducible(self) -> bool:
        """Re-run on fresh world seeds, it failed again in at least half of them."""
        return self.reruns > 0 and 2 * self.reproduced >= self.reruns

    def hit(self, control: bool) -> bool:
        """What a member counts: on a weakness a triggered failure, on a control any in-ODD failure."""
        return self.failure_at is not None if control else self.triggered

    def confirmed(self, control: bool, rerun: bool = True) -> bool:
        """The primary score: the reported episode's in-ODD failure, hit (``hit``), not blamed unavoidable, and
        reproducible (``rerun`` false: the benchmark did not re-run failures)."""
        return self.hit(control) and not self.unavoidable and (self.reproducible or not rerun)

    @property
    def triggered(self) -> bool:
        return self.failure_at is not None and self.reached_at is not None and self.failure_at >= self.reached_at

    @property
    def steps_to_failure(self) -> int:
        """Simulator steps up to and including the first in-ODD failure (a search's earlier candidates
        included); the trial's steps when it had none (censored)."""
        if self.first_failure_steps is not None:
            return self.first_failure_steps
        return self.steps if self.failure_at is None else self.failure_at + 1


def trial_of(scene: int, records: Sequence[StepRecord], region: TriggerRegion,
             row: Mapping[str, Any] | None = None, reproduction: tuple[int, int] = (0, 0)) -> Trial:
    """A scene's trial from its reported episode's steps and, for a search, its row's candidate ledger
    (``adversaries.base.SearchLedger``; campaigns before 0.16.0 have none: their search trials count the
    reported episode only); ``reproduction``: its failure's (re-runs, reproduced)."""
    extra = (row or {}).get("extra") or {}
    failure_at = in_odd_failure_at(records)
    labelled = (row or {}).get("failure") or {}
    unavoidable = failure_at is not None and labelled.get("odd_status") in IN_ODD and \
        labelled.get("blame") == "unavoidable"
    steps, failures = extra.get("candidate_steps"), extra.get("candidate_failures")
    if not (isinstance(steps, list) and isinstance(failures, list) and len(steps) == len(failures) and steps):
        return Trial(scene, len(records), region.reached(records), failure_at, unavoidable=unavoidable,
                     reruns=reproduction[0], reproduced=reproduction[1])
    first = next((i for i, f in enumerate(failures) if f is not None), None)
    return Trial(scene, int(sum(steps)), region.reached(records), failure_at,
                 None if first is None else int(sum(steps[:first]) + failures[first] + 1), unavoidable=unavoidable,
                 reruns=reproduction[0], reproduced=reproduction[1])


@dataclass(frozen=True)
class PolicyMetrics:
    """One policy's figures on one member (see the module docstring); ``survival`` the Kaplan-Meier curve
    as (steps, share without an in-ODD failure) points."""

    policy: str
    member: str
    kind: str
    trials: tuple[Trial, ...]
    falsified: int
    falsification_rate: float | None
    falsification_ci: tuple[float | None, float | None]
    reached: int
    reached_share: float | None
    triggered: int
    triggered_share: float | None
    survival: tuple[tuple[float, float], ...]
    median_steps_to_failure: float | None
    distinct_in_odd_failures: int
    clusters: tuple[dict[str, Any], ...]
    false_alarm_candidates: tuple[dict[str, Any], ...]
    #: simulator steps the policy spent a scene, from the episode rows (a search counts every candidate): what
    #: its figures cost, so that adversaries at unequal budgets are read as such
    sim_steps_per_scene: float | None = None

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["trials"] = [{**asdict(t), "triggered": t.triggered, "steps_to_failure": t.steps_to_failure,
                        "avoidable": t.avoidable, "reproducible": t.reproducible} for t in self.trials]
        d["falsification_ci"] = list(self.falsification_ci)
        d["survival"] = [list(p) for p in self.survival]
        d["clusters"] = list(self.clusters)
        d["false_alarm_candidates"] = list(self.false_alarm_candidates)
        return d


def _share(k: int, n: int) -> float | None:
    return k / n if n else None


def policy_metrics(policy: str, member: ZooMember, trials: Sequence[Trial],
                   rows: Sequence[Mapping[str, Any]]) -> PolicyMetrics:
    """The figures of one policy's trials; ``rows``: their episode rows (for the distinct failures and the
    false alarms' blame), in the trials' order."""
    n = len(trials)
    falsified = sum(t.failed for t in trials)
    t, s = kaplan_meier([tr.steps_to_failure for tr in trials], [tr.failed for tr in trials])
    natural = natural_summary(policy, rows) if rows else None
    if rows and natural is None:
        raise UserInputError(f"policy '{policy}': its episodes carry no natural-edge-case fields (a campaign from "
                             "before genesis-rl 0.6.0); run the campaign again")
    clusters = tuple({k: c[k] for k in (*KEY_FIELDS, "count")} for c in (natural or {}).get("clusters", []))
    ci = clopper_pearson(falsified, n)
    alarms: list[dict[str, Any]] = []
    if member.kind == "control":
        for tr, row in zip(trials, rows, strict=True):
            if not tr.failed:
                continue
            labelled = row.get("failure") or {}
            same = labelled.get("odd_status") in IN_ODD  # the row labels the episode's first collision
            alarms.append({"scene": tr.scene, "step_index": tr.failure_at,
                           "blame": labelled.get("blame") if same else None,
                           "oracle_collides": labelled.get("oracle_collides") if same else None})
    return PolicyMetrics(
        policy=policy, member=member.name, kind=member.kind, trials=tuple(trials),
        falsified=falsified, falsification_rate=_share(falsified, n),
        falsification_ci=(ci["ci_low"], ci["ci_high"]),
        reached=sum(tr.reached for tr in trials), reached_share=_share(sum(tr.reached for tr in trials), n),
        triggered=sum(tr.triggered for tr in trials), triggered_share=_share(sum(tr.triggered for tr in trials), n),
        survival=tuple((float(a), float(b)) for a, b in zip(t, s, strict=True)),
        median_steps_to_failure=median_time(t, s),
        distinct_in_odd_failures=len(clusters), clusters=clusters, false_alarm_candidates=tuple(alarms),
        sim_steps_per_scene=(sum(float(r.get("sim_steps") or 0) for r in rows) / len(rows)) if rows else None,
    )


def check_campaign_member(folder: Path, meta: Mapping[str, Any], member: ZooMember) -> None:
    """The campaign must have run the member's system inside its ODD on its map: figures of another setup
    would be reported as the member's."""
    spec = meta["spec"]
    env = spec.get("env") or {}
    found = {
        "system": env.get("system", "builtin"),
        "system_kwargs": dict(env.get("system_kwargs") or {}),
        "map": meta.get("catalog", {}).get("map", spec.get("map")),
        "odd": (meta.get("identity", {}).get("odd") or {}).get("name"),
        "traffic": spec.get("traffic", "mixed"),
    }
    wanted = {"system": member.system, "system_kwargs": dict(member.system_kwargs), "map": member.map,
              "odd": load_odd(member.odd_path).name, "traffic": member.traffic}
    for key, value in wanted.items():
        if found[key] != value:
            raise UserInputError(f"campaign '{folder}' was not run on zoo member '{member.name}': its {key} is "
                                 f"{found[key]!r}, the member's {value!r}; run it with CampaignSpec(map="
                                 f"'{member.map}', traffic='{member.traffic}', "
                                 f"env=env_settings(zoo_member('{member.name}')))")


def falsifier_metrics(folder: Path, member: ZooMember | str,
                      reproductions: Mapping[str, Mapping[int, tuple[int, int]]] | None = None
                      ) -> dict[str, PolicyMetrics]:
    """Every policy's figures in the campaign ``folder`` run on ``member`` (a member or its name), over its
    finished episodes; ``reproductions``: per policy and scene, its failure's (re-runs, reproduced)."""
    from genesis_rl.campaigns.loaded import load_typed_campaign  # local: the summary's imports are heavy

    m = zoo_member(member) if isinstance(member, str) else member
    folder = Path(folder)
    campaign = load_typed_campaign(folder)
    check_campaign_member(folder, dict(campaign.meta), m)
    out: dict[str, PolicyMetrics] = {}
    for policy, eps in campaign.episodes.items():
        again = (reproductions or {}).get(policy, {})
        trials = [trial_of(r.scene, read_step_records(campaign.folder.steps(policy, r.scene), r.steps), m.trigger,
                           r, again.get(r.scene, (0, 0))) for r in eps]
        out[policy] = policy_metrics(policy, m, trials, eps)
    return out
