#!/usr/bin/env bash
# podman as this repository runs it where no Docker engine runs (tests, build-image.sh):
# Debian's podman 4.3 with runc, images kept under .cache/container/storage.
#
#   scripts/podman.sh images            # any podman command
#
# runc, not crun: crun refuses hybrid cgroup hierarchies. default_ulimits = []: podman's
# default RLIMIT_NOFILE is higher than an unprivileged-looking host allows
# ("setrlimit RLIMIT_NOFILE: Operation not permitted"). cgroupfs and a file events log:
# no systemd here.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
DIR="$ROOT/.cache/container"
mkdir -p "$DIR"
CONF="$DIR/containers.conf"
if [ ! -f "$CONF" ]; then
    cat > "$CONF.tmp" <<'CONF'
[containers]
default_ulimits = []

[engine]
runtime = "runc"
cgroup_manager = "cgroupfs"
events_logger = "file"
CONF
    mv "$CONF.tmp" "$CONF"
fi
export CONTAINERS_CONF="$CONF"
# The run root holds locks and mounts: short, on the local disk, one per checkout.
RUNROOT="/run/spindle-podman-$(printf %s "$ROOT" | sha256sum | cut -c1-12)"
exec podman --root "$DIR/storage" --runroot "$RUNROOT" --storage-driver overlay "$@"
