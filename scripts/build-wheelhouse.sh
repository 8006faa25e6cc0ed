#!/usr/bin/env bash
# Downloads every wheel the image installs into wheelhouse/ (the image build then needs
# no package index: an air-gapped plant carries this folder to the box with the sources).
#
#   scripts/build-wheelhouse.sh                      # for x86-64 boxes
#   ARCH=aarch64 scripts/build-wheelhouse.sh         # for arm64 boxes
#
# The set is requirements.lock, checked against its sha256 hashes, plus the build
# backend pyproject.toml pins (setuptools). Wheels only, for CPython 3.11, so the
# folder does not depend on the machine that downloads it. Done once per lock: a
# stamp records which requirements.lock the folder holds.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3.11}
ARCH=${ARCH:-x86_64}
GLIBC_MINOR=36  # the base image is Debian bookworm: glibc 2.36
OUT=${WHEELHOUSE:-wheelhouse}
STAMP="$OUT/.lock-sha256"
want="$(sha256sum requirements.lock | cut -d' ' -f1) $ARCH"
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
    exit 0
fi
rm -rf "$OUT" && mkdir -p "$OUT"
target=(--only-binary=:all: --python-version 3.11 --implementation cp --abi cp311 --abi abi3
        --abi none --platform any --platform "manylinux2014_$ARCH")
for minor in $(seq 17 "$GLIBC_MINOR"); do  # every manylinux glibc level the base can run
    target+=(--platform "manylinux_2_${minor}_$ARCH")
done
"$PYTHON" -m pip download --quiet --disable-pip-version-check --no-deps --require-hashes \
    "${target[@]}" -r requirements.lock -d "$OUT"
backend=$("$PYTHON" -c "import tomllib; print(tomllib.load(open('pyproject.toml','rb'))['build-system']['requires'][0])")
"$PYTHON" -m pip download --quiet --disable-pip-version-check --no-deps \
    "${target[@]}" "$backend" -d "$OUT"
echo "$want" > "$STAMP"
echo "wheelhouse: $(ls "$OUT"/*.whl | wc -l) wheels in $OUT ($(du -sh "$OUT" | cut -f1))"
