"""``genesis-rl export``: a campaign's failures as a detector training set (YOLO, COCO) or as OpenSCENARIO files.

A top-level command (as ``realism_cmd``): it joins ``evaluation.export`` (the frames and labels) and
``openscenario`` (the scenarios), and ``openscenario`` itself replays records through ``evaluation``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from genesis_rl.core.errors import UserInputError


def run(args: argparse.Namespace) -> int:
    from genesis_rl.exports.dataset import FORMATS, export_dataset

    formats = (*FORMATS, "openscenario")
    if args.format not in formats:
        raise UserInputError(f"--format '{args.format}' is unknown; allowed: {', '.join(formats)}")
    if args.format == "openscenario" or args.scenarios:
        from genesis_rl.exports.openscenario.export import minor_version
        from genesis_rl.exports.openscenario.schema import require_scenariogeneration

        minor_version(args.osc_version)
        require_scenariogeneration()
    if args.format == "openscenario":
        if args.policies or args.scenarios:
            raise UserInputError("--policies and --scenarios go with --format yolo or coco; openscenario exports "
                                 "every failing episode's record")
        from genesis_rl.exports.openscenario.export import export_openscenario

        result = export_openscenario(Path(args.campaign), Path(args.out), args.force, args.osc_version,
                                     not args.no_check, args.all_records, args.weights, progress=not args.quiet)
        print(json.dumps(result, indent=2))
        return 0
    policies = [p.strip() for p in args.policies.split(",")] if args.policies else None
    if policies is not None and not all(policies):
        raise UserInputError(f"--policies '{args.policies}' has an empty name; give a comma list such as agent,random")
    add = None
    if args.scenarios:
        from genesis_rl.exports.openscenario.export import export_scenarios, summary_line

        def add(tmp: Path) -> dict:
            index = export_scenarios(Path(args.campaign), tmp, args.osc_version, not args.no_check,
                                     args.all_records, args.weights, progress=not args.quiet)
            return {"scenarios": len(index["scenarios"]), "scenarios_summary": summary_line(index)}
    result = export_dataset(Path(args.campaign), args.format, Path(args.out), args.force, policies, add)
    print(json.dumps(result, indent=2))
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    ex = subparsers.add_parser(
        "export", help="export failures: frames with ground-truth labels (YOLO, COCO) or OpenSCENARIO scenarios",
        description="Export a campaign's failures. yolo/coco: the frames kept around each collision with the "
                    "simulator's boxes (--scenarios adds each failure's OpenSCENARIO file). openscenario: one "
                    ".xosc per failing episode (a campaign's records/, or one record file) beside its map's "
                    ".xodr, checked against ASAM's schema, read back, and driven again on lite "
                    "(docs/openscenario.md).")
    ex.add_argument("campaign", help="campaign folder (openscenario: or one record file, CAMPAIGN/records/NAME.json)")
    ex.add_argument("--format", default="yolo", help="yolo, coco or openscenario")
    ex.add_argument("--policies", default=None, help="comma list of policies to export (default: all; yolo/coco)")
    ex.add_argument("--out", required=True, help="output directory")
    ex.add_argument("--force", action="store_true", help="replace an existing output")
    ex.add_argument("--scenarios", action="store_true",
                    help="yolo/coco: also write each failure's OpenSCENARIO file into the export (scenarios/)")
    ex.add_argument("--osc-version", default="1.0",
                    help="OpenSCENARIO version: 1.0 (default, what CARLA ScenarioRunner reads), 1.1, 1.2 "
                         "(adds wind and road wetness), 1.3")
    ex.add_argument("--no-check", action="store_true",
                    help="skip the checks (schema, read-back, lite replay from the file: about 25 s a scenario)")
    ex.add_argument("--all-records", action="store_true",
                    help="every record of the campaign, not only those of failing episodes")
    ex.add_argument("--weights", default=None, help="the system's detector weights, when the records' are not "
                                                    "found (as replay --weights)")
    ex.add_argument("--quiet", action="store_true", help="no progress bar")
    ex.set_defaults(func=run)
    return ex
