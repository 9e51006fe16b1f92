#!/usr/bin/env bash
# The test command: install, lint, format check, then the whole test suite on two pytest-xdist
# workers (tests/scheduling.py: which tests share a worker, the longest first).
#   FLEETMAP_TEST_WORKERS  how many (default 2; 0 runs the suite in this process)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
.venv/bin/ruff check .
.venv/bin/ruff format --check .
workers=${FLEETMAP_TEST_WORKERS:-2}
xdist=()
[ "$workers" = 0 ] || xdist=(-n "$workers" --dist loadgroup)
.venv/bin/python -m pytest -p no:dash "${xdist[@]}" "$@"
