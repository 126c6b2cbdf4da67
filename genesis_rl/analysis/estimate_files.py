"""A finished ``genesis-rl estimate`` folder as the pages read it that show its rate beside the failures found
(the benchmark's leaderboard, a campaign's report).

It lives in ``evaluation`` because the report does: the estimation package builds on evaluation (its statistics
and failure clusters), so evaluation reads an estimate's JSON here without importing the estimator."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.parsing import read_json

#: the schema of ``estimate.json``
SCHEMA = "genesis-rl/estimate"


def load_estimate(folder: Path, member: str | None = None) -> dict[str, Any]:
    """A finished estimate's summary (for the benchmark's page), refused, naming the folder, when it is not
    one, is unfinished, or estimates another member."""
    data = read_json(Path(folder) / "estimate.json", f"estimate '{folder}': estimate.json")
    if not isinstance(data, dict) or data.get("schema") != SCHEMA or not data.get("done"):
        raise UserInputError(f"'{folder}' holds no finished estimate (run genesis-rl estimate --out {folder}, or "
                             "--resume it)")
    found = data["spec"]["member"]
    if member is not None and found != member:
        raise UserInputError(f"the estimate in '{folder}' is of member '{found}', not '{member}'")
    keys = ("estimate", "episode_s", "per_hour", "per_hour_ci95", "episodes_spent", "clusters", "in_odd_share")
    return {"folder": str(folder), "spec": data["spec"], **{k: data.get(k) for k in keys}}


def estimate_line(rate: Mapping[str, Any]) -> str:
    """How often the member fails under natural conditions, per ``genesis-rl estimate`` (``load_estimate``)."""
    e = rate["estimate"]
    lo, hi = e["ci95"]
    carried = "; ".join(f"{c['share']:.0%} {c['cluster']}" for c in (rate.get("clusters") or [])[:3])
    return (f"Failure rate under natural conditions: {e['probability']:.3g} per {rate['episode_s']:g} s episode "
            f"[95 % CI {lo:.3g}, {hi:.3g}], {rate['per_hour']:.3g} an hour driven ({e['method']}, "
            f"{rate['episodes_spent']} episodes, {rate['folder']})" + (f"; carried by {carried}" if carried else ""))


def check_same_system(rate: Mapping[str, Any], campaign_env: Mapping[str, Any], campaign_map: str) -> None:
    """Refuse, naming the field, an estimate of another system, ODD or map than the campaign's."""
    from genesis_rl.sut.zoo.members import env_settings, zoo_member

    member = zoo_member(rate["spec"]["member"])
    mine = env_settings(member)
    theirs = {"system": campaign_env.get("system", "builtin"), "odd": campaign_env.get("odd"), "map": campaign_map}
    for field in ("system", "odd", "map"):
        a, b = mine[field], theirs[field]
        if field == "odd":
            a, b = (None if v is None else Path(str(v)).name for v in (a, b))
        if a != b:
            raise UserInputError(f"--estimate '{rate['folder']}' estimates member '{member.name}' ({field} = {a!r}); "
                                 f"the campaign has {field} = {b!r}")
