#!/usr/bin/env bash
# Builds the gateway image from the repository's Dockerfile with podman, with no registry:
#
#   scripts/build-image.sh [TAG]        # default spindle-thermal-gateway:<version>
#   scripts/build-image.sh --prepare    # steps 1–2 and the dependencies stage only
#
# 1. the base: Debian bookworm with Python 3.11 from Debian's own packages
#    (mmdebstrap --variant=minbase), imported as localhost/spindle-base:bookworm;
#    its rootfs tarball is cached with the images (scripts/podman.sh; made once, ~250 MB);
# 2. the wheelhouse (scripts/build-wheelhouse.sh, once per requirements.lock);
# 3. podman build --build-arg BASE=localhost/spindle-base:bookworm; the layers are
#    cached, so a rebuild after a code change takes seconds.
# --prepare stops after the Dockerfile's `dependencies` stage (the locked wheels
# installed into /opt/venv): what changes only with requirements.lock, made once when
# the machine is set up (scripts/setup-system.sh), so the full build in the tests
# starts from the cached stage and builds only the layers the code changes.
# With a registry at hand, `docker build .` uses the Dockerfile's default base instead.
set -euo pipefail
cd "$(dirname "$0")/.."
PREPARE=0
if [ "${1:-}" = "--prepare" ]; then
    PREPARE=1
    shift
fi
VERSION=$(python3 -c "import tomllib; print(tomllib.load(open('pyproject.toml','rb'))['project']['version'])")
TAG=${1:-spindle-thermal-gateway:$VERSION}
BASE=localhost/spindle-base:bookworm
ROOTFS="${SPINDLE_CONTAINER_CACHE:-/var/cache/spindle-gateway/container}/rootfs-bookworm-py311.tar"
PODMAN=scripts/podman.sh

if [ ! -f "$ROOTFS" ]; then
    echo "building the base root filesystem with mmdebstrap (once, a few minutes)"
    mkdir -p "$(dirname "$ROOTFS")"
    mmdebstrap --quiet --variant=minbase --format=tar \
        --include=python3.11,python3.11-venv,python3-pip,ca-certificates \
        bookworm "$ROOTFS.part"
    mv "$ROOTFS.part" "$ROOTFS"
fi
if ! "$PODMAN" image exists "$BASE"; then
    "$PODMAN" import --quiet "$ROOTFS" "$BASE" >/dev/null
fi
bash scripts/build-wheelhouse.sh
if ((PREPARE)); then
    "$PODMAN" build --quiet --format docker --layers --network none --target dependencies \
        --build-arg "BASE=$BASE" -t spindle-gateway-dependencies:latest . >/dev/null
    echo "prepared $BASE and the dependencies stage"
    exit 0
fi
# --format docker: OCI images have no HEALTHCHECK; the Docker format keeps it.
# --network none: the build needs no network at all (the wheelhouse is in the context).
"$PODMAN" build --quiet --format docker --layers --network none \
    --build-arg "BASE=$BASE" -t "$TAG" . >/dev/null
echo "built $TAG on $BASE"
