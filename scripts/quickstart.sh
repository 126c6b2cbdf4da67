#!/usr/bin/env bash
# The main job on the embedded simulator: set up, generate both scene catalogs (the paper's counts),
# render the showcase pictures, drive the system under test in clear weather and in fog, train a small
# weather agent, evaluate it against the sunny and random baselines on held-out highway scenes and write
# the report, its failures exported as OpenSCENARIO files (checked against ASAM's schema and driven again on
# lite from the files) and linked from the report. Outputs go to out/quickstart/ (about 10 minutes on 2 CPU cores).
set -euo pipefail
cd "$(dirname "$0")/.."
GENESIS_EXTRAS="${GENESIS_EXTRAS:-dev,openscenario}" bash scripts/setup.sh
OUT="${OUT:-out/quickstart}"
mkdir -p "$OUT"
.venv/bin/genesis-rl scenes --map urban --seed 0 --out "$OUT/urban_scenes.json" --force
.venv/bin/genesis-rl scenes --map highway --seed 0 --out "$OUT/highway_scenes.json" --force
.venv/bin/genesis-rl render --map urban --scene 0 --weather clear_noon --out "$OUT/render_urban" --force
.venv/bin/genesis-rl render --sweep --map highway --scene 0 --out "$OUT/sweep_highway" --force
# the system under test on a test-town scene: clear noon, then dense fog
.venv/bin/genesis-rl drive --catalog "$OUT/highway_scenes.json" --scene 9 --weather clear_noon \
    --out "$OUT/drive_clear" --force --quiet
.venv/bin/genesis-rl drive --catalog "$OUT/highway_scenes.json" --scene 9 --weather dense_fog \
    --out "$OUT/drive_fog" --force --quiet
# a small adversarial weather agent (configs/paper.toml is the paper's full schedule)
.venv/bin/genesis-rl train --config configs/quickstart.toml --out "$OUT/run" --force
# evaluate it on held-out scenes of the test town against the baselines, and label every failure against
# a highway day-time ODD (inside or not, blame, naturalness, distinct failures: docs/odd.md); report.html
.venv/bin/genesis-rl evaluate --agent "$OUT/run" --catalog "$OUT/highway_scenes.json" --scenes 10 --steps 256 \
    --policies sunny,random,agent --odd configs/odd/highway_day.toml --odd-label-only --workers 2 \
    --out "$OUT/eval" --force
# every failure as an OpenSCENARIO 1.0 file beside the map's OpenDRIVE (docs/openscenario.md), then the report
# again, linking them
.venv/bin/genesis-rl export "$OUT/eval" --format openscenario --out "$OUT/scenarios" --force --quiet
.venv/bin/genesis-rl report "$OUT/eval" --scenarios "$OUT/scenarios" --force
echo "[quickstart] done. Report: $OUT/eval/report.html; scenarios: $OUT/scenarios/scenarios.json"
