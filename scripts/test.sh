#!/usr/bin/env bash
# Set up (if needed), lint, and run the whole test suite, slow tests included as a second step.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
echo "[test] ruff"
.venv/bin/ruff check genesis_rl tests
echo "[test] pytest (fast)"
.venv/bin/python -m pytest -q -m "not slow" "$@"
echo "[test] pytest (slow)"
set +e
.venv/bin/python -m pytest -q -m slow "$@"
rc=$?
set -e
# exit code 5 = no slow tests collected: not a failure
if [ "$rc" -ne 0 ] && [ "$rc" -ne 5 ]; then exit "$rc"; fi
