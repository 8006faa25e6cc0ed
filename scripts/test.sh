#!/usr/bin/env bash
# The whole test suite: lint first (a style error is a red CI), then pytest.
# Called by `make test` after .venv/ exists; installs nothing by hand.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv
bash scripts/setup-system.sh
"$VENV/bin/ruff" check .
# Both cores: one worker per core, each test file on one worker (its servers start once).
"$VENV/bin/pytest" -q -n 2 --dist loadfile --durations=15 "$@"
