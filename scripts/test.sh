#!/usr/bin/env bash
# The whole test suite: lint, format and types first (any error is a red CI), then pytest.
# Called by `make test` after .venv/ exists; installs nothing by hand.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv
bash scripts/setup-system.sh
"$VENV/bin/ruff" check .
"$VENV/bin/ruff" format --check .
# The type hints are checked too (the packages and options in pyproject.toml [tool.mypy]).
"$VENV/bin/mypy"
# Four workers on two cores: most end-to-end tests spend their time waiting on protocol
# time (outages, back-offs, cycles in real time), so two per core keep both cores busy;
# each test file stays on one worker (its servers start once), the longest files first
# (tests/conftest.py LONGEST_FIRST).
# One BLAS/OpenMP thread per worker: four workers each spinning two threads on two cores
# starve the tests that wait on wall-clock protocol timeouts (an RTU reply in 0.5 s).
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
"$VENV/bin/pytest" -q -n 4 --dist loadfile --no-loadscope-reorder --durations=15 "$@"
