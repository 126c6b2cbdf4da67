"""Near misses for the hardening's data: collision-free episodes whose time to collision with the lead fell to a
threshold inside the ODD, and their camera frames up to the closest approach.

A campaign keeps camera frames only around collisions, so a near miss has none on disk. Its record holds all that
drove it (scene, episode seed, start weather, schedule, system and weights), so the frames are rendered again by
replaying the episode up to its closest approach, and the replay is checked against the campaign's own step data.
The time to collision is the surrogate safety measure of traffic-conflict studies: the gap to the lead over the
closing speed; 1.5 s is the usual line for a serious conflict (Hydén 1987; Hayward 1972 used 1 s)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.errors import UserInputError

#: in-ODD step labels (a failure's ``odd_status``): the closest approach must be inside the ODD or on its boundary
IN_ODD = ("inside", "boundary")
#: a closing speed below this [m/s] is no conflict, whatever the gap
MIN_CLOSING = 0.5


def closest_approach(rows: Sequence[Mapping[str, Any]]) -> tuple[int, float] | None:
    """(step, time to collision [s]) of the in-ODD step where the time to collision with the lead was smallest;
    None when the ego never closed in on a lead inside the ODD."""
    best: tuple[int, float] | None = None
    for row in rows:
        gap, ego, lead = row.get("true_lead_distance"), row.get("ego_speed"), row.get("lead_speed")
        if row.get("odd_status") not in IN_ODD or gap is None or ego is None or lead is None:
            continue
        closing = float(ego) - float(lead)
        if not (math.isfinite(float(gap)) and closing >= MIN_CLOSING):
            continue
        ttc = float(gap) / closing
        if best is None or ttc < best[1]:
            best = (int(row["step"]), ttc)
    return best


def near_misses(folder: Path, ttc_s: float) -> dict[tuple[str, int], dict[str, float]]:
    """The campaign's in-ODD near misses: (policy, scene) -> {step, ttc, gap, ego_speed} at the closest approach of
    each collision-free episode whose time to collision fell to ``ttc_s`` or below (0: none are looked for)."""
    from genesis_rl.campaigns.campaign_files import read_steps
    from genesis_rl.campaigns.loaded import load_typed_campaign

    if ttc_s <= 0:
        return {}
    campaign = load_typed_campaign(folder)
    found: dict[tuple[str, int], dict[str, float]] = {}
    for policy, episodes in campaign.episodes.items():
        for ep in episodes:
            if ep.collided:  # a failure, not a near miss
                continue
            steps = read_steps(campaign.folder.steps(policy, ep.scene),
                               columns=["step", "true_lead_distance", "ego_speed", "lead_speed", "odd_status"],
                               steps=ep.steps)
            closest = closest_approach(steps)
            if closest is not None and closest[1] <= ttc_s:
                row = next(r for r in steps if r["step"] == closest[0])
                # the gap and speed there: what the replay must reproduce (render_frames)
                found[(policy, ep.scene)] = {"step": closest[0], "ttc": round(closest[1], 3),
                                                     "gap": float(row["true_lead_distance"]),
                                                     "ego_speed": float(row["ego_speed"])}
    return found


def render_frames(folder: Path, misses: Mapping[tuple[str, int], Mapping[str, float]], out: Path, weights: Path,
                  frames_before: int, stride: int, progress: bool = False) -> dict[str, Any]:
    """Replay each near miss (as ``near_misses`` gives it) from its record up to its closest approach and write the
    frames a collision would have kept (``frames_before`` steps before it, every ``stride``-th) as
    ``out/frames/POLICY/scene_NNNN/step_SSSS.jpg``, the campaign's layout. An episode whose replay departs from the
    recorded gap and speed there is skipped and named, as is one without a record (``records = "failures"`` records
    collisions and proximity violations only)."""
    from tqdm import tqdm

    from genesis_rl.campaigns.episodes import write_jpeg
    from genesis_rl.campaigns.records import load_record, replay_record

    written: list[str] = []
    departed: list[str] = []
    unrecorded: list[str] = []
    for (policy, scene), miss in tqdm(sorted(misses.items()), desc="near misses: replay", unit="episode",
                                      disable=not progress):
        step = int(miss["step"])
        name = f"{policy}_scene_{scene:04d}"
        path = CampaignFolder(folder).records_dir / f"{name}.json"
        if not path.is_file():  # a campaign with records = "failures" writes none for a conflict without proximity
            unrecorded.append(name)
            continue
        rec = dict(load_record(path))
        rec["schedule"] = rec["schedule"][:step]  # steps are numbered from 1: step s is schedule row s - 1
        rec["steps"] = step
        replay = replay_record(rec, weights=str(weights), keep_frames=True)
        last = replay["records"][-1]
        if last.step != step or not (math.isclose(last.lead.true_distance, miss["gap"], abs_tol=1e-6)
                                     and math.isclose(last.ego.speed, miss["ego_speed"], abs_tol=1e-6)):
            departed.append(name)
            continue
        for rec_step, rgb in zip(replay["records"], replay["frames"], strict=True):
            if step - frames_before <= rec_step.step <= step and (step - rec_step.step) % stride == 0:
                write_jpeg(CampaignFolder(out).frames(policy, scene) / f"step_{rec_step.step:04d}.jpg", rgb)
        written.append(name)
    if departed and not written:
        raise UserInputError(f"no near miss of '{folder}' replayed as the campaign recorded it "
                             f"({', '.join(departed)}); the weights or the simulator differ from the campaign's")
    return {"episodes": written, "departed": departed, "unrecorded": unrecorded}
