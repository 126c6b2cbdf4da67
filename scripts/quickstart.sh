#!/usr/bin/env bash
# The main job on the embedded simulator: set up, generate both scene catalogs (the paper's counts),
# and render the showcase pictures (once the renderer lands). Outputs go to out/quickstart/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
OUT="${OUT:-out/quickstart}"
mkdir -p "$OUT"
.venv/bin/genesis-rl scenes --map urban --seed 0 --out "$OUT/urban_scenes.json" --force
.venv/bin/genesis-rl scenes --map highway --seed 0 --out "$OUT/highway_scenes.json" --force
if .venv/bin/genesis-rl --help | grep -q " render"; then
    .venv/bin/genesis-rl render --map urban --scene 0 --weather clear_noon --out "$OUT/render_urban" --force
    .venv/bin/genesis-rl render --sweep --map highway --scene 0 --out "$OUT/sweep_highway" --force
fi
echo "[quickstart] done: $OUT"
