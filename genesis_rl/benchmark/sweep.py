"""The ground truth of a zoo member, measured: its failure rate with the weather held at each value of one knob,
inside its trigger region and around it (``genesis-rl zoo sweep``).

A member's trigger region is stated before any adversary runs; the sweep is the evidence that the region is
where the failures are. For each value the sweep runs one campaign of the ``sunny`` policy (the weather held
where it starts) on the member's system, map, ODD and env, starting from the member's start weather with the
knob set to the value, and counts the in-ODD failures as the benchmark does (``benchmark/metrics.py``), with
an exact 95 % interval. Values whose start lies outside the member's ODD are listed and not driven: the
region's surroundings that count are inside the domain. Every campaign is an ordinary campaign folder
(``OUT/campaigns/value_NN``), so ``genesis-rl report`` opens it and ``--resume`` continues a sweep.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import output_folder
from genesis_rl.core.files.io_utils import atomic_write_json
from genesis_rl.sut.zoo.members import ZooMember, env_settings, zoo_member
from genesis_rl.sut.zoo.trigger import CONDITION_FLAGS
from genesis_rl.world.knobs import KNOBS

if TYPE_CHECKING:
    from genesis_rl.world.odd.domain import ODD

SCHEMA = "genesis-rl/zoo-sweep"


@dataclass(frozen=True)
class SweepSpec:
    """What decides a sweep's results: the member, the knob and its values, scenes per value, the campaign
    seed and the steps per episode (None: the member's own)."""

    member: str
    knob: str
    values: tuple[float, ...]
    scenes: int = 8
    seed: int = 0
    steps: int | None = None
    #: other knobs held at one value for every swept value (a region over two knobs: sweep one, hold the other)
    hold: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        zoo_member(self.member)
        if self.knob not in KNOBS:
            raise UserInputError(f"--knob = '{self.knob}' is unknown; allowed: {', '.join(KNOBS)}")
        if not self.values:
            raise UserInputError("--values: give at least one value")
        for v in self.values:
            _check_value("--values", self.knob, v)
        hold = tuple((str(k), float(v)) for k, v in self.hold)  # a spec read back from JSON holds lists
        object.__setattr__(self, "hold", hold)
        for k, v in hold:
            if k not in KNOBS:
                raise UserInputError(f"--hold: knob '{k}' is unknown; allowed: {', '.join(KNOBS)}")
            _check_value("--hold", k, v)
        held = [k for k, _ in hold]
        if self.knob in held or len(set(held)) != len(held):
            raise UserInputError(f"--hold: {held} names a knob twice or the swept knob '{self.knob}'")
        if len(set(self.values)) != len(self.values):
            raise UserInputError(f"--values: {list(self.values)} names a value twice")
        if self.scenes < 1 or self.seed < 0 or (self.steps is not None and self.steps < 1):
            raise UserInputError(f"zoo sweep: scenes = {self.scenes} must be >= 1, seed = {self.seed} >= 0 and steps "
                                 f"= {self.steps} >= 1 (or none: the member's own)")

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"member": self.member, "knob": self.knob, "values": list(self.values),
                               "scenes": self.scenes, "seed": self.seed, "steps": self.steps}
        if self.hold:  # only when set, so that a sweep written before --hold existed still resumes
            out["hold"] = [list(kv) for kv in self.hold]
        return out


def _check_value(flag: str, knob: str, value: float) -> None:
    spec = KNOBS[knob]
    if not (math.isfinite(value) and spec.low <= value <= spec.high):
        raise UserInputError(f"{flag}: {value!r} is outside {knob}'s range [{spec.low:g}, {spec.high:g}]")


def in_region(member: ZooMember, knob: str, value: float, hold: Sequence[tuple[str, float]] = ()) -> bool | None:
    """Whether the start with ``knob`` at ``value`` (and the ``hold`` knobs at theirs) lies inside the member's
    trigger region: every bound judged on the whole start weather, knob bounds on its knobs and condition bounds
    (``visibility_m``, ``rain_mm_h``) on lite's conditions model. None: the member is a control (no region), or
    its region names a flag that only a step can tell (``sun_glare`` depends on where the camera looks); the
    sweep's rows then count the episodes that reached the region instead."""
    if member.trigger.empty or any(b.quantity in CONDITION_FLAGS for b in member.trigger.bounds):
        return None
    from genesis_rl.world.knobs import parse_weather

    weather = parse_weather(start_weather(member, knob, value, hold))
    conditions = None
    if any(b.is_condition for b in member.trigger.bounds):
        from genesis_rl.world.odd.conditions import conditions_model

        conditions = conditions_model("lite").conditions(weather, None)
    knobs = weather.as_dict()
    return all(b.low <= (float(getattr(conditions, b.quantity)) if b.is_condition else knobs[b.quantity]) < b.high
               for b in member.trigger.bounds)


def start_weather(member: ZooMember, knob: str, value: float, hold: Sequence[tuple[str, float]] = ()) -> str:
    """The member's start weather with ``knob`` at ``value`` and the ``hold`` knobs at theirs
    (``EnvConfig.start_weather`` text)."""
    base = str(member.env.get("start_weather", "clear_noon"))
    overrides = {**dict(hold), knob: value}
    # the swept and held knobs replace the member's own start values (fog_braking starts in mist: fog_density=26)
    kept = [part for part in base.split(",") if part.split("=", 1)[0].strip() not in overrides]
    set_ = [f"{k}={v:g}" for k, v in overrides.items()]
    return ",".join([*kept, *set_]) if kept else ",".join(["clear_noon", *set_])


def value_folder(out: Path, index: int) -> Path:
    return Path(out) / "campaigns" / f"value_{index:02d}"


def _inside_odd(odd: ODD, member: ZooMember, knob: str, value: float,
                hold: Sequence[tuple[str, float]] = ()) -> bool:
    from genesis_rl.world.knobs import parse_weather
    from genesis_rl.world.odd.conditions import conditions_model

    weather = parse_weather(start_weather(member, knob, value, hold))
    return odd.contains(conditions_model("lite").conditions(weather, None), weather)


def run_sweep(spec: SweepSpec, out: Path, *, force: bool = False, resume: bool = False, workers: int = 1,
              progress: bool = True) -> dict[str, Any]:
    """Run every value's campaign not yet finished, then write ``sweep.json`` and ``sweep.png``; returns the
    sweep's table."""
    from tqdm import tqdm

    from genesis_rl import __version__
    from genesis_rl.benchmark.campaign_once import run_campaign_once
    from genesis_rl.benchmark.metrics import falsifier_metrics
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.world.odd.domain import load_odd

    member = zoo_member(spec.member)
    out = Path(out)
    if resume and not (out / "sweep.json").exists():
        raise UserInputError(f"--resume: '{out}' holds no sweep.json; start it without --resume")
    with output_folder.claim(out, "sweep", force, resume=resume):
        if resume:
            found = output_folder.recorded_spec(out / "sweep.json", "sweep")
            output_folder.check_same_settings("sweep", out, found, spec.to_json())
        else:
            output_folder.replace(out, "sweep")
            atomic_write_json(out / "sweep.json", {"schema": SCHEMA, "version": __version__,
                                                   "spec": spec.to_json(), "rows": []}, indent=1)
        steps = spec.steps or int(member.env.get("episode_steps", 512))
        odd = load_odd(member.odd_path)
        rows: list[dict[str, Any]] = []
        for i, value in enumerate(tqdm(spec.values, desc=f"sweep {spec.knob}", unit="value", disable=not progress)):
            row: dict[str, Any] = {"value": value, "in_region": in_region(member, spec.knob, value, spec.hold)}
            if not _inside_odd(odd, member, spec.knob, value, spec.hold):
                rows.append({**row, "inside_odd": False})
                continue
            folder = value_folder(out, i)
            env = {**env_settings(member), "start_weather": start_weather(member, spec.knob, value, spec.hold)}
            run_campaign_once(CampaignSpec(policies=("sunny",), map=member.map, scenes=spec.scenes, seed=spec.seed,
                                           steps=steps, env=env, traffic=member.traffic), folder, workers=workers)
            m = falsifier_metrics(folder, member)["sunny"]
            rows.append({**row, "inside_odd": True, "trials": len(m.trials), "failed": m.falsified,
                         "rate": m.falsification_rate, "ci95": list(m.falsification_ci),
                         "steps_to_failure": [t.steps_to_failure for t in m.trials if t.failed],
                         "reached": sum(t.reached for t in m.trials),
                         "failed_when_reached": sum(t.failed and t.reached for t in m.trials),
                         "campaign": str(folder.relative_to(out))})
        table = {"schema": SCHEMA, "version": __version__, "spec": spec.to_json(), "member_kind": member.kind,
                 "trigger": member.trigger.describe(), "rows": rows, **_inside_outside(rows)}
        atomic_write_json(out / "sweep.json", table, indent=1)
        plot_sweep(table, out / "sweep.png")
    return table


def _inside_outside(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Failures pooled over the driven values whose start lies inside the region, outside it and all of them (a
    control's: it has no region), and over the episodes that reached the region at some step and those that
    never did, each with its exact interval."""
    from genesis_rl.core.stats import clopper_pearson

    def pool(n: int, k: int) -> dict[str, Any]:
        ci = clopper_pearson(k, n)
        return {"trials": n, "failed": k, "rate": ci["rate"], "ci95": [ci["ci_low"], ci["ci_high"]]}

    pooled: dict[str, Any] = {}
    for key, flags in (("inside_region", (True,)), ("outside_region", (False,)), ("driven", (True, False, None))):
        driven = [r for r in rows if r.get("inside_odd") and r["in_region"] in flags]
        pooled[key] = pool(sum(r["trials"] for r in driven), sum(r["failed"] for r in driven))
    # by what each episode did rather than where it started: those that entered the region at some step and
    # those that never did (rows written before 0.19 carry no counts and are left out)
    counted = [r for r in rows if r.get("inside_odd") and "reached" in r]
    n_in, k_in = sum(r["reached"] for r in counted), sum(r["failed_when_reached"] for r in counted)
    pooled["reached_region"] = pool(n_in, k_in)
    pooled["never_reached"] = pool(sum(r["trials"] for r in counted) - n_in, sum(r["failed"] for r in counted) - k_in)
    return pooled


def plot_sweep(table: dict[str, Any], path: Path) -> None:
    """Failure rate against the knob's value with exact intervals; the trigger region shaded."""
    from genesis_rl.core.plotting import pyplot

    plt = pyplot()

    from genesis_rl.core.files.io_utils import atomic_write

    spec, rows = table["spec"], [r for r in table["rows"] if r.get("inside_odd")]
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    member = zoo_member(spec["member"])
    for b in member.trigger.bounds:
        if b.quantity == spec["knob"]:
            # an open end (-inf, inf) is drawn to just past the swept values; a finite one where it is
            lo = b.low if math.isfinite(b.low) else min(spec["values"]) - 1.0
            hi = b.high if math.isfinite(b.high) else max(spec["values"]) + 1.0
            ax.axvspan(lo, hi, color="#f4a261", alpha=0.25, label=f"trigger region: {member.trigger.describe()}")
    if rows:
        xs = [r["value"] for r in rows]
        ys = [r["rate"] for r in rows]
        lo_err = [r["rate"] - r["ci95"][0] for r in rows]
        hi_err = [r["ci95"][1] - r["rate"] for r in rows]
        ax.errorbar(xs, ys, yerr=[lo_err, hi_err], fmt="o-", color="#264653", capsize=3,
                    label="in-ODD failure rate (exact 95 % CI)")
        counted = [r for r in rows if "reached" in r and r["trials"]]
        if member.kind == "weakness" and counted:  # what each episode did, whatever its start (glare: the heading)
            span = (max(xs) - min(xs)) if len(xs) > 1 else 1.0
            ax.bar([r["value"] for r in counted], [r["reached"] / r["trials"] for r in counted],
                   width=0.03 * span, color="#bbbbbb", alpha=0.7, zorder=1, label="episodes that reached the region")
        inside = [r for r in rows if r["in_region"]]  # judged on the whole start: condition bounds included
        if inside:
            shaded = any(b.quantity == spec["knob"] for b in member.trigger.bounds)
            ax.scatter([r["value"] for r in inside], [r["rate"] for r in inside], s=70, color="#e76f51", zorder=3,
                       label="start inside the trigger region" + ("" if shaded else f": {member.trigger.describe()}"))
    for n, r in enumerate(r for r in table["rows"] if not r.get("inside_odd")):
        ax.axvline(r["value"], color="#999999", ls=":", lw=1, label="outside the ODD: not driven" if n == 0 else None)
    unit = KNOBS[spec["knob"]].unit
    ax.set_xlabel(f"{spec['knob']} [{unit}], held" if unit else f"{spec['knob']}, held")
    ax.set_ylabel("episodes with an in-ODD failure")
    ax.set_ylim(-0.03, 1.03)
    held = "".join(f", {k}={v:g} held" for k, v in spec.get("hold", ()))
    ax.set_title(f"{spec['member']} ({member.kind}): {spec['scenes']} scenes a value, seed {spec['seed']}{held}",
                 fontsize=10)
    ax.legend(fontsize=8, loc="best", framealpha=0.9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    atomic_write(path, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)
