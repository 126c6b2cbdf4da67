"""``genesis-rl compare``: policies from different campaigns, paired scene by scene.

An agent is evaluated in its own campaign and the baselines in another (they need no agent, and a search
takes hours), yet the protocol compares them on the same scenes. This reads each ``LABEL=CAMPAIGN:POLICY``,
checks that the campaigns are comparable (map, episode length, system under test, ODD and weather dynamics,
and the same episode seed for every shared scene) and reports, on the shared scenes, every policy's
figures and the first one's paired differences to each of the others (bootstrap CI, wins/ties/losses,
sign-flip p-value: ``evaluation.stats``).
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.campaigns.summary import load_campaign
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.stats import bootstrap_mean_ci, clopper_pearson, paired_comparison
from genesis_rl.core.text import terminal_safe
from genesis_rl.labels.distinct import natural_summary
from genesis_rl.world.odd.domain import IN_ODD

#: what two campaigns must share to be compared, read from campaign.json
SAME = (("map", lambda m: m.get("catalog", {}).get("map", m["spec"]["map"])),
        ("steps", lambda m: m["spec"]["steps"]),
        ("system", lambda m: _system_key(m.get("identity", {}).get("system"))),
        ("odd", lambda m: m.get("identity", {}).get("odd")),
        ("dynamics", lambda m: m["spec"]["env"].get("dynamics", "paper")))


def _system_key(identity: Any) -> Any:
    """The system under test as it decides: its class, weights (by hash: a path differs between machines) and
    settings; not the package version that ran it (``compare`` lists the versions instead)."""
    if not isinstance(identity, dict):
        return identity
    return {k: v for k, v in identity.items() if k != "version" and not (k == "weights" and "weights_sha256"
                                                                         in identity)}


def _brief(value: Any) -> str:
    """A campaign setting as a user knows it: an ODD by its name, a system by its class and weights."""
    if isinstance(value, dict):
        if "name" in value:
            return str(value["name"])
        if "class" in value:
            return " ".join(str(value[k]) for k in ("class", "weights", "weights_sha256") if k in value)
    return json.dumps(value, default=str)[:120]


@dataclass(frozen=True)
class Series:
    label: str
    folder: Path
    policy: str


def parse_series(text: str) -> Series:
    """``LABEL=CAMPAIGN:POLICY`` (``CAMPAIGN:POLICY`` takes the policy as its label)."""
    label, sep, rest = text.partition("=")
    if not sep:
        label, rest = "", text
    folder, sep, policy = rest.rpartition(":")
    if not sep or not folder or not policy:
        raise UserInputError(f"'{text}': expected LABEL=CAMPAIGN:POLICY, e.g. agent=runs/sac_s0/eval:agent")
    return Series(label or policy, Path(folder), policy)


def _in_odd_collision(row: dict[str, Any]) -> float:
    """1 for a collision inside the campaign's ODD (or any collision when it has none), else 0."""
    failure = row.get("failure") or {}
    return float(bool(failure) and failure.get("odd_status", "no ODD") in (*IN_ODD, "no ODD"))


#: per-episode figures paired across policies: (key, what it is, how it is read from an episode row)
PAIRED = (("return", "return", lambda r: float(r["return"])),
          ("collision", "episodes with a collision", lambda r: float(r["collision_events"] > 0)),
          ("in_odd_collision", "episodes with an in-ODD collision", _in_odd_collision),
          ("proximity", "episodes following closer than the proximity rule", lambda r: float(r["proximity"] > 0)))


def compare(series: Sequence[Series], seed: int = 0) -> dict[str, Any]:
    """Every series' figures on the scenes all of them played, and the first series against each other."""
    if len(series) < 2:
        raise UserInputError("compare needs at least two LABEL=CAMPAIGN:POLICY series")
    labels = [s.label for s in series]
    if len(set(labels)) != len(labels):
        raise UserInputError(f"labels must differ: {', '.join(labels)}; name them LABEL=CAMPAIGN:POLICY")
    cache: dict[Path, tuple[dict[str, Any], dict[str, list[dict[str, Any]]]]] = {}
    rows: dict[str, dict[int, dict[str, Any]]] = {}
    seeds: dict[int, tuple[int, str]] = {}
    first_meta: dict[str, Any] | None = None
    for s in series:
        if s.folder not in cache:
            cache[s.folder] = load_campaign(s.folder)
        meta, by_policy = cache[s.folder]
        if s.policy not in by_policy:
            raise UserInputError(f"'{s.folder}' has no policy '{s.policy}'; it has {', '.join(by_policy)}")
        if first_meta is None:
            first_meta = meta
        for name, read in SAME:
            if read(meta) != read(first_meta):
                raise UserInputError(f"'{s.folder}' and '{series[0].folder}' differ in {name} "
                                     f"({_brief(read(meta))} against {_brief(read(first_meta))}): their policies "
                                     "cannot be paired")
        for scene, episode_seed in meta["scenes"]:
            known = seeds.setdefault(int(scene), (int(episode_seed), str(s.folder)))
            if known[0] != int(episode_seed):
                raise UserInputError(f"scene {scene} ran with episode seed {episode_seed} in '{s.folder}' and "
                                     f"{known[0]} in '{known[1]}': evaluate both with the same --seed")
        rows[s.label] = {int(r["scene"]): r for r in by_policy[s.policy]}
    shared = sorted(set.intersection(*(set(r) for r in rows.values())))
    if not shared:
        raise UserInputError("the series share no finished scene")
    policies: dict[str, Any] = {}
    for s in series:
        eps = [rows[s.label][sc] for sc in shared]
        natural = natural_summary(s.policy, eps)
        collisions = sum(1 for e in eps if e["collision_events"] > 0)
        in_odd = int(sum(_in_odd_collision(e) for e in eps))
        policies[s.label] = {
            "campaign": str(s.folder), "policy": s.policy, "episodes": len(eps),
            "sim_steps": int(sum(e["sim_steps"] for e in eps)),
            "collisions": collisions, "in_odd_collisions": in_odd,
            "in_odd_collision_rate": clopper_pearson(in_odd, len(eps)),
            "distinct_in_odd_failures": natural["distinct_in_odd_failures"] if natural else None,
            "proximity_episodes": sum(1 for e in eps if e["proximity"] > 0),
            # seeded by the label, so an interval does not depend on the order of the series
            "return": bootstrap_mean_ci([e["return"] for e in eps], seed + zlib.crc32(s.label.encode()) % 100_003),
            "returns": [round(float(e["return"]), 3) for e in eps],  # per shared scene, in scene order
            "mean_iou": round(float(np.mean([e["mean_iou"] for e in eps])), 4),
            "knobs_final": {k: round(float(np.mean([e["knobs_final"][k] for e in eps])), 2)
                            for k in eps[0]["knobs_final"]},
        }
    first = series[0].label
    comparisons = {
        f"{first}_vs_{s.label}": {key: paired_comparison([read(rows[first][sc]) for sc in shared],
                                                         [read(rows[s.label][sc]) for sc in shared], seed + 7)
                                  for key, _, read in PAIRED}
        for s in series[1:]}
    odd = SAME[3][1](first_meta) if first_meta else None
    versions = sorted({str(meta.get("package_version")) for meta, _ in cache.values()})
    return {"scenes": shared, "map": SAME[0][1](first_meta) if first_meta else None,
            "odd": odd.get("name") if isinstance(odd, dict) else None, "package_versions": versions,
            "policies": policies, "comparisons": comparisons}


def _ci(stats: dict[str, Any], digits: int = 1) -> str:
    return f"{stats['mean']:.{digits}f} [{stats['ci_low']:.{digits}f}, {stats['ci_high']:.{digits}f}]"


def compare_markdown(result: dict[str, Any]) -> str:
    n = len(result["scenes"])
    knobs = next(iter(result["policies"].values()))["knobs_final"]
    domain = f"inside the ODD `{result['odd']}`" if result.get("odd") else \
        "no ODD declared, so every collision counts as in-ODD"
    lines = [f"{n} shared scenes on `{result['map']}`, {domain}; final knobs: the mean at the episode's end of "
             f"{' / '.join(knobs)}."]
    if len(result.get("package_versions", ())) > 1:
        lines.append(f"The campaigns ran with genesis-rl {', '.join(result['package_versions'])} (the same system "
                     "class, weights and settings).")
    lines += ["",
             "| policy | sim steps | episodes with a collision | in-ODD collisions [95% CI of the rate] | "
             "distinct in-ODD failures | episodes with a proximity violation | return [95% CI] | mean IoU | "
             "final knobs |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for label, p in result["policies"].items():
        rate = p["in_odd_collision_rate"]
        knobs = " / ".join(f"{v:g}" for v in p["knobs_final"].values())
        lines.append(f"| {label} | {p['sim_steps']:,} | {p['collisions']} / {n} | {p['in_odd_collisions']} "
                     f"[{100 * rate['ci_low']:.0f}, {100 * rate['ci_high']:.0f} %] | "
                     f"{'-' if p['distinct_in_odd_failures'] is None else p['distinct_in_odd_failures']} | "
                     f"{p['proximity_episodes']} | {_ci(p['return'])} | {p['mean_iou']:.3f} | {knobs} |")
    lines += ["", "| comparison | return difference [95% CI], wins/ties/losses, p | collision episodes "
              "difference | in-ODD collision episodes difference |", "| --- | --- | --- | --- |"]
    for name, c in result["comparisons"].items():
        cells = []
        for key in ("return", "collision", "in_odd_collision"):
            x = c[key]
            digits = 1 if key == "return" else 2
            p = "-" if x["p_value"] is None else f"{x['p_value']:.4f}" if x["p_value"] < 0.001 else \
                f"{x['p_value']:.3f}"
            cells.append(f"{_ci(x['difference'], digits)}, {x['wins']}/{x['ties']}/{x['losses']}, p {p}")
        lines.append(f"| {name.replace('_vs_', ' - ')} | " + " | ".join(cells) + " |")
    return terminal_safe("\n".join(lines) + "\n", keep="\n")  # names from a shared file print as text
