"""An estimate in one sentence, for the pages that show it beside the failures found (the benchmark's
leaderboard, a campaign's report)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from genesis_rl.errors import UserInputError


def estimate_line(rate: Mapping[str, Any]) -> str:
    """How often the member fails under natural conditions, per ``genesis-rl estimate`` (``load_estimate``)."""
    e = rate["estimate"]
    lo, hi = e["ci95"]
    carried = "; ".join(f"{c['share']:.0%} {c['cluster']}" for c in (rate.get("clusters") or [])[:3])
    return (f"Failure rate under natural conditions: {e['probability']:.2g} per {rate['episode_s']:g} s episode "
            f"[95 % CI {lo:.2g}, {hi:.2g}], {rate['per_hour']:.3g} an hour driven ({e['method']}, "
            f"{rate['episodes_spent']} episodes, {rate['folder']})" + (f"; carried by {carried}" if carried else ""))


def check_same_system(rate: Mapping[str, Any], campaign_env: Mapping[str, Any], campaign_map: str) -> None:
    """Refuse, naming the field, an estimate of another system, ODD or map than the campaign's."""
    from pathlib import Path

    from genesis_rl.zoo.members import env_settings, zoo_member

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
