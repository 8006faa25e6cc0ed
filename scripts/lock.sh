#!/usr/bin/env bash
# Regenerates the dependency locks from pyproject.toml, with every file's sha256:
#   requirements.lock      the runtime set (what the image installs)
#   requirements-dev.lock  the runtime set, same versions, plus the dev tools (make install)
# Run after changing a pin in pyproject.toml, and commit both files.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3.11}
TOOLS=.cache/lock-venv
if [ ! -x "$TOOLS/bin/pip-compile" ]; then
    "$PYTHON" -m venv "$TOOLS"
    "$TOOLS/bin/pip" install --quiet pip-tools==7.6.2
fi
common=(--quiet --generate-hashes --strip-extras --allow-unsafe --no-emit-index-url
        --no-emit-find-links --no-header --annotation-style=line)
"$TOOLS/bin/pip-compile" "${common[@]}" -o requirements.lock pyproject.toml
"$TOOLS/bin/pip-compile" "${common[@]}" --extra dev -c requirements.lock \
    -o requirements-dev.lock pyproject.toml
