#!/usr/bin/env bash
# podman as this repository runs it where no Docker engine runs (tests, build-image.sh):
# Debian's podman 4.3 with runc, images kept in one machine-wide cache
# ($SPINDLE_CONTAINER_CACHE, default /var/cache/spindle-gateway/container), so every
# checkout on the machine (a fresh clone too) reuses the base and the layers.
#
#   scripts/podman.sh images            # any podman command
#
# runc, not crun: crun refuses hybrid cgroup hierarchies. default_ulimits = []: podman's
# default RLIMIT_NOFILE is higher than an unprivileged-looking host allows
# ("setrlimit RLIMIT_NOFILE: Operation not permitted"). cgroupfs and a file events log:
# no systemd here.
set -euo pipefail
DIR="${SPINDLE_CONTAINER_CACHE:-/var/cache/spindle-gateway/container}"
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
# The run root holds locks and mounts: short, on the local disk, one per storage.
RUNROOT="/run/spindle-podman-$(printf %s "$DIR" | sha256sum | cut -c1-12)"
exec podman --root "$DIR/storage" --runroot "$RUNROOT" --storage-driver overlay "$@"
