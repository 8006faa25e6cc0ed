#!/usr/bin/env bash
# Builds InfluxDB 2.7.12 (the version deploy/docker-compose.yml ships) from its Go module
# into .cache/bin/influxd2, so the tests run against the server the deployment uses.
# About 12 minutes cold on two cores, 2-3 minutes with a warm Go cache; nothing when the
# binary exists. Output goes to stdout/stderr: callers redirect it to a log.
#
# Why the detours:
# - `go install ...@v2.7.12` is refused (its go.mod has a replace directive), so the module
#   is downloaded and built from a writable copy.
# - flux's Rust core is built through influxdata's pkg-config wrapper (pinned in go.mod).
# - flux pins Rust 1.72, which rustup cannot download here: RUSTUP_TOOLCHAIN=stable.
# - flux-core denies warnings and newer Rust warns more; RUSTFLAGS does not reach its
#   build-dependency, so a RUSTC_WRAPPER appends --cap-lints warn to every rustc call.
set -euo pipefail
cd "$(dirname "$0")/.."

VERSION=2.7.12
BIN="$PWD/.cache/bin"
OUT="$BIN/influxd2"
WORK="$PWD/.cache/influxd2-build"

if [ -x "$OUT" ] && [ "${1:-}" != "--force" ]; then
    echo "$OUT exists"
    exit 0
fi
command -v go >/dev/null || export PATH="$PATH:/usr/local/go/bin"
command -v go >/dev/null || { echo "Go is needed to build influxd $VERSION"; exit 1; }
[ -d "$HOME/.cargo/bin" ] && export PATH="$PATH:$HOME/.cargo/bin"
command -v cargo >/dev/null || { echo "Rust (cargo) is needed to build influxd $VERSION"; exit 1; }

mkdir -p "$BIN" "$WORK"
echo "$(date -u +%FT%TZ) downloading github.com/influxdata/influxdb/v2@v$VERSION"
MODDIR=$(go mod download -json "github.com/influxdata/influxdb/v2@v$VERSION" |
    sed -n 's/^[[:space:]]*"Dir": "\(.*\)",\?$/\1/p')
[ -d "$MODDIR" ] || { echo "go mod download gave no module folder"; exit 1; }

SRC="$WORK/influxdb-$VERSION"
rm -rf "$SRC"
cp -r "$MODDIR" "$SRC"
chmod -R u+w "$SRC"

cat >"$WORK/rustc-wrapper" <<'EOF'
#!/bin/sh
exec "$@" --cap-lints warn
EOF
chmod +x "$WORK/rustc-wrapper"

cd "$SRC"
echo "$(date -u +%FT%TZ) building influxdata's pkg-config wrapper"
go build -o "$WORK/pkg-config" github.com/influxdata/pkg-config
echo "$(date -u +%FT%TZ) building influxd $VERSION (flux's Rust core first)"
PKG_CONFIG="$WORK/pkg-config" RUSTUP_TOOLCHAIN=stable RUSTC_WRAPPER="$WORK/rustc-wrapper" \
    go build -trimpath -tags sqlite_foreign_keys,sqlite_json \
    -ldflags "-s -w -X main.version=$VERSION" -o "$OUT.tmp" ./cmd/influxd
mv "$OUT.tmp" "$OUT"
cd - >/dev/null
rm -rf "$SRC"
echo "$(date -u +%FT%TZ) built $OUT"
"$OUT" version
