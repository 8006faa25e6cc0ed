#!/usr/bin/env bash
# Build the Telegraf reference poller used by benchmarks/poll_vs_telegraf.py.
#
# Only the plugins the benchmark needs are compiled in (custom build tags), so
# the build is a fraction of a full Telegraf.  The Go module and build caches
# stay in the usual places (~/go, ~/.cache/go-build), so a second build only
# links.  The binary lands in .cache/bin/telegraf of this checkout.
set -euo pipefail

TELEGRAF_VERSION="${TELEGRAF_VERSION:-v1.39.3}"
GO="${GO:-$(command -v go || echo /usr/local/go/bin/go)}"
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN_DIR="$ROOT/.cache/bin"
TARGET="$BIN_DIR/telegraf"

if [[ -x "$TARGET" ]] && "$TARGET" --version 2>/dev/null | grep -q "${TELEGRAF_VERSION#v}"; then
    echo "telegraf ${TELEGRAF_VERSION} already at $TARGET"
    exit 0
fi

mkdir -p "$BIN_DIR"
# GOBIN puts the binary straight into .cache/bin; GOPATH/GOMODCACHE are left
# at their defaults (~/go) so the module downloads are shared between builds.
# The version is stamped the way Telegraf's Makefile does (go install alone says
# "unknown"), so the benchmark's JSON and the check above can name it.
GOBIN="$BIN_DIR" "$GO" install \
    -tags "custom,inputs.modbus,inputs.opcua,outputs.discard" \
    -ldflags "-X github.com/influxdata/telegraf/internal.Version=${TELEGRAF_VERSION#v}" \
    "github.com/influxdata/telegraf/cmd/telegraf@${TELEGRAF_VERSION}"
"$TARGET" --version
