#!/usr/bin/env bash
# Set up (if needed), lint, and run the whole test suite, slow tests included as a second step.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
echo "[test] ruff"
.venv/bin/ruff check genesis_rl tests
echo "[test] pytest (all tests, slow and render ones included)"
.venv/bin/python -m pytest -q "$@"
