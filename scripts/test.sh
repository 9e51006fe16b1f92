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
if [ "$workers" != 0 ]; then
    xdist=(-n "$workers" --dist loadgroup)
    # the cores shared out: each worker's BLAS and OpenMP kernels (numpy, torch, Open3D,
    # faiss) get its share, so one worker's idle threads do not spin against the other's
    # (docs/BENCHMARKS.md, session 19: on 2 cores the suite 426 -> 365 s, CPU 724 -> 596 s)
    share=$(($(nproc) / workers))
    [ "$share" -ge 1 ] || share=1
    export OPENBLAS_NUM_THREADS=${OPENBLAS_NUM_THREADS:-$share} OMP_NUM_THREADS=${OMP_NUM_THREADS:-$share}
fi
.venv/bin/python -m pytest -p no:dash "${xdist[@]}" "$@"
