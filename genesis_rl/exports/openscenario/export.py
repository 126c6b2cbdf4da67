"""``genesis-rl export SOURCE --format openscenario``: edge-case records as checked OpenSCENARIO files.

For every failing episode of a campaign (its ``records/*.json``), or one record file:

1. trace: replay the record on lite and read every vehicle's path (``trace``);
2. write ``scenarios/NAME.xosc`` beside ``scenarios/MAP.xodr`` (``writer``; the map once per map);
3. check, unless ``--no-check``: the scenario against ASAM's XSD of its version and the map against
   OpenDRIVE 1.7's; the scenario read back with scenariogeneration's reader gives the same vehicles, start
   poses and speeds, trajectories and weather within :data:`TOLERANCES`; lite driven from the parsed file
   (``lite_replay``) reproduces the failure: the ego's first collision with the same vehicle within a step,
   or, for an episode without a collision, the same rules violated.

``scenarios.json`` lists each scenario with its checks; a scenario that fails a check is still written, and
the index says which check failed and by how much.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from genesis_rl.campaigns.layout import CampaignFolder
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.io_utils import atomic_write_json, atomic_write_text
from genesis_rl.core.parsing import read_json
from genesis_rl.exports.openscenario.reader import ParsedScenario, read_scenario
from genesis_rl.exports.openscenario.schema import validate_opendrive, validate_scenario
from genesis_rl.exports.openscenario.trace import EpisodeTrace, trace_record
from genesis_rl.exports.openscenario.writer import (
    VERTEX_TOLERANCE,
    rear_axle,
    vehicle_name,
    write_scenario,
)
from genesis_rl.world.step_record import StepRecord

SCENARIO_FOLDER = "scenarios"
INDEX = "scenarios.json"
#: read-back tolerances: positions [m] (the polyline's tolerance per axis, in the plane, plus the rear axle's
#: round trip in floating point), headings [rad], speeds [m/s], knobs (relative to their range)
TOLERANCES = {"position_m": math.sqrt(2.0) * float(VERTEX_TOLERANCE[0]) + 1e-9,
              "heading_rad": float(VERTEX_TOLERANCE[3]) + 1e-9,
              "speed_m_s": 1e-9, "knob_share": 1e-7}
VERSIONS = {"1.0": 0, "1.1": 1, "1.2": 2, "1.3": 3}


def minor_version(version: str) -> int:
    """The minor version of ``--osc-version`` (1.0 -> 0)."""
    if version not in VERSIONS:
        raise UserInputError(f"--osc-version '{version}' is unknown; allowed: {', '.join(VERSIONS)}")
    return VERSIONS[version]


def failing_records(folder: Path, every: bool = False) -> list[Path]:
    """A campaign's records of failing episodes (``every``: all its records), or the one record file given."""
    if folder.is_file():
        return [folder]
    records = CampaignFolder(folder).records_dir
    if not records.is_dir():
        raise UserInputError(f"'{folder}' is neither a record file nor a campaign folder with records/ "
                             "(campaigns keep a record of every failing episode there)")
    paths = sorted(records.glob("*.json"))
    if not every:
        paths = [p for p in paths if read_json(p, "record").get("failure") is not None]
    return paths


def roundtrip_errors(trace: EpisodeTrace, parsed: ParsedScenario) -> dict[str, Any]:
    """Largest differences between the trace and what scenariogeneration's reader gave back of its file."""
    from genesis_rl.world.knobs import KNOBS

    out: dict[str, Any] = {"vehicles": [len(trace.vehicles), len(parsed.vehicles)]}
    pos = head = speed = 0.0
    for track in trace.vehicles:
        v = parsed.vehicle(vehicle_name(track.vehicle_id))
        xr, yr = rear_axle(track)
        pos = max(pos, math.hypot(v.start[0] - xr[0], v.start[1] - yr[0]))
        head = max(head, abs(math.remainder(v.start[3] - track.yaw[0], 2 * math.pi)))
        speed = max(speed, abs(v.start_speed - track.speed[0]))
        if v.times is None or v.poses is None:
            out["missing_trajectory"] = v.name
            continue
        x = np.interp(trace.times, v.times, v.poses[:, 0])
        y = np.interp(trace.times, v.times, v.poses[:, 1])
        h = np.interp(trace.times, v.times, np.unwrap(v.poses[:, 3]))
        pos = max(pos, float(np.max(np.hypot(x - xr, y - yr))))
        head = max(head, float(np.max(np.abs(np.remainder(h - track.yaw + np.pi, 2 * np.pi) - np.pi))))
    # the weather lite gets from the file at the start and before every step, against what was recorded
    from genesis_rl.exports.openscenario.lite_replay import scenario_weathers

    start, weathers, _ = scenario_weathers(parsed, trace.dt, len(trace.schedule))
    written = [trace.start_weather] + [dict(zip(trace.knob_names, map(float, row), strict=True))
                                       for row in trace.schedule]
    knob = 0.0
    for got, want in zip([start, *weathers], written, strict=True):
        for name, spec in KNOBS.items():
            if spec.is_actor or name not in want:
                continue
            diff = abs(got[name] - want[name])
            if spec.wraps:
                diff = min(diff, spec.span - diff)
            knob = max(knob, diff / spec.span)
    out.update({"start_and_path_position_m": float(pos), "heading_rad": float(head),
                "start_speed_m_s": float(speed), "knob_share": float(knob)})
    out["ok"] = bool(out["vehicles"][0] == out["vehicles"][1] and "missing_trajectory" not in out
                 and pos <= TOLERANCES["position_m"] and head <= TOLERANCES["heading_rad"]
                 and speed <= TOLERANCES["speed_m_s"] and knob <= TOLERANCES["knob_share"])
    return out


def first_difference(recorded: list[StepRecord], replayed: list[StepRecord]) -> dict[str, Any] | None:
    """The first step where lite driven from the file leaves the recorded drive, and what differs there first
    (the vehicles in the image, the detections, the ego's speed, its control, a collision); None: the same to
    the last step."""
    for a, b in zip(recorded, replayed, strict=False):
        boxes = [(g.vehicle_id, g.box_xyxy) for g in a.perception.gt_boxes] == [
            (g.vehicle_id, g.box_xyxy) for g in b.perception.gt_boxes]
        what = [name for name, same in (
            ("vehicles in the image", boxes), ("detections", a.perception.detections == b.perception.detections),
            ("ego speed", a.ego.speed == b.ego.speed),
            ("control", (a.ego.throttle, a.ego.brake, a.ego.steer) == (b.ego.throttle, b.ego.brake, b.ego.steer)),
            ("collision", (a.collision.collided, a.collision.other_id) == (b.collision.collided, b.collision.other_id)))
            if not same]
        if what:
            return {"step": a.step, "differs": what}
    return None


def reproduction(trace: EpisodeTrace, parsed: ParsedScenario, weights: str | None,
                 recorded: list[StepRecord] | None = None) -> dict[str, Any]:
    """Drive lite from the parsed file and compare its failure with the trace's; with the ``recorded`` steps,
    also where the drive from the file first leaves them, and, when the failure does not reproduce, why."""
    from genesis_rl.exports.openscenario.lite_replay import drive_scenario

    drive = drive_scenario(parsed, weights=weights)
    original = {"first_collision_step": trace.first_collision_step, "collision_with": trace.collision_with,
                "violations": trace.violations}
    replayed = {"first_collision_step": drive.first_collision_step, "collision_with": drive.collision_with,
                "violations": drive.violations}
    if trace.first_collision_step is not None:
        same = (drive.first_collision_step is not None and drive.collision_with == trace.collision_with
                and abs(drive.first_collision_step - trace.first_collision_step) <= 1)
    else:
        same = ({k for k, v in trace.violations.items() if v > 0} == {k for k, v in drive.violations.items() if v > 0})
    standard = sorted(n for n, s in drive.knob_sources.items() if s == "standard")
    out = {"reproduced": bool(same), "original": original, "from_scenario": replayed,
           "knobs_from_standard": standard,
           "knobs_from_genesis_command": sorted(n for n, s in drive.knob_sources.items() if s == "genesis")}
    if recorded is not None:
        diff = first_difference(recorded, drive.records)
        out["first_difference"] = diff
        if not same:
            out["why_not"] = ("the drive from the file is the recorded one to the last step, so the failure "
                              "check itself disagrees" if diff is None else
                              f"the drive from the file leaves the recorded one at step {diff['step']}: "
                              f"{', '.join(diff['differs'])} differ(s) first")
    return out


def export_scenarios(source: Path, out: Path, version: str = "1.0", check: bool = True, every: bool = False,
                     weights: str | None = None, progress: bool = True,
                     on_scenario: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Write ``out/scenarios/`` (the .xosc files and their maps) and ``out/scenarios.json``; returns the index.
    ``out`` must exist (the caller claims it)."""
    from genesis_rl.campaigns.records import load_record
    from genesis_rl.sim.lite.maps import load_map
    from genesis_rl.sim.lite.maps.opendrive import to_opendrive

    minor = minor_version(version)
    paths = failing_records(source, every)
    folder = out / SCENARIO_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    maps: dict[str, dict[str, Any]] = {}
    entries = []
    for path in tqdm(paths, desc="openscenario", unit="scenario", disable=not progress):
        rec = load_record(path)
        trace, replay = trace_record(rec, path.stem, weights)
        if trace.map not in maps:
            xodr = folder / f"{trace.map}.xodr"
            atomic_write_text(xodr, to_opendrive(load_map(trace.map)))
            checked = validate_opendrive(xodr) if check else None
            maps[trace.map] = {"file": f"{SCENARIO_FOLDER}/{xodr.name}", "schema": None if checked is None
                               else checked.schema, "valid": None if checked is None else checked.valid,
                               "errors": [] if checked is None else list(checked.errors[:5])}
        xosc = folder / f"{path.stem}.xosc"
        write_scenario(trace, xosc, f"{trace.map}.xodr", minor)
        entry: dict[str, Any] = {
            "record": str(path), "scenario": f"{SCENARIO_FOLDER}/{xosc.name}", "map": maps[trace.map]["file"],
            "version": version, "bytes": xosc.stat().st_size, "vehicles": len(trace.vehicles),
            "steps": len(trace.schedule), "record_replayed_exactly": bool(replay["reproduced"]),
            "first_collision_step": trace.first_collision_step,
            "collision_with": None if trace.collision_with is None else vehicle_name(trace.collision_with)}
        if check:
            v = validate_scenario(xosc)
            entry["schema"] = {"file": v.schema, "valid": v.valid, "errors": list(v.errors[:5])}
            parsed = read_scenario(xosc)
            entry["read_back"] = roundtrip_errors(trace, parsed)
            entry["replay"] = reproduction(trace, parsed, weights, replay["records"])
        entries.append(entry)
        if on_scenario is not None:
            on_scenario(entry)
    index: dict[str, Any] = {"version": version, "scenarios": entries, "maps": maps}
    if check:
        index["checked"] = {
            "scenarios": len(entries),
            "schema_valid": sum(e["schema"]["valid"] for e in entries),
            "read_back_ok": sum(e["read_back"]["ok"] for e in entries),
            "reproduced_on_lite": sum(e["replay"]["reproduced"] for e in entries),
            "maps_valid": sum(bool(m["valid"]) for m in maps.values()) if maps else None,
            "tolerances": TOLERANCES}
    atomic_write_json(out / INDEX, index, indent=2)
    return index


def summary_line(index: dict[str, Any]) -> str:
    c = index.get("checked")
    n = len(index["scenarios"])
    if n == 0:
        return "no failing episode to export (pass --all-records to export every record)"
    if c is None:
        return f"{n} scenario(s) written (not checked: --no-check)"
    line = (f"{n} scenario(s): {c['schema_valid']} valid against ASAM's XSD, {c['read_back_ok']} read back within "
            f"tolerance, {c['reproduced_on_lite']} of {n} ({100.0 * c['reproduced_on_lite'] / n:.0f} %) reproduce "
            f"their failure on lite from the file; maps valid: {c['maps_valid']}/{len(index['maps'])}")
    missed = [f"{e['scenario']} ({e['replay'].get('why_not', 'not reproduced')})" for e in index["scenarios"]
              if not e["replay"]["reproduced"]]
    return line + ("; not reproduced: " + "; ".join(missed) if missed else "")



def export_openscenario(source: Path, out: Path, force: bool = False, version: str = "1.0", check: bool = True,
                        every: bool = False, weights: str | None = None, progress: bool = True) -> dict[str, Any]:
    """``genesis-rl export SOURCE --format openscenario --out OUT``: a folder of its own, claimed and put in
    place whole like the other exports (nothing half-written is left at ``out``)."""
    import shutil

    from genesis_rl.core.files import output_folder
    from genesis_rl.core.files.io_utils import remove_tree

    minor_version(version)
    output_folder.check_folder_inputs(out, [source])
    failing_records(source, every)  # refuses a source that is neither a record nor a campaign with records/
    with output_folder.claim(out, "export", force, inputs=[source]):
        tmp = out.with_name(f".{out.name}.partial")
        try:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            output_folder.write_marker(tmp, "export")
            index = export_scenarios(source, tmp, version, check, every, weights, progress)
            result = {"out": str(out), "format": "openscenario", "scenarios": len(index["scenarios"]),
                      "summary": summary_line(index), **({"checked": index["checked"]} if check else {})}
            atomic_write_json(tmp / "export.json", result, indent=2)
            if out.exists():
                remove_tree(out)
            tmp.rename(out)
            return result
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
