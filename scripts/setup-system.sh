#!/usr/bin/env bash
# System packages the tests need, installed only when missing:
#   socat  (a serial pty pair for Modbus RTU without hardware)
#   mbpoll (an independent libmodbus-based Modbus master)
#   node-opcua (an independent OPC UA client, pinned in tests/node/package-lock.json)
#   influxd 1.8.10 (a real time-series server; built once with Go into .cache/bin)
#   podman, runc, mmdebstrap (the gateway image is built and run: tests/test_container.py),
#   and the image's base and locked dependencies (scripts/build-image.sh --prepare)
set -euo pipefail
cd "$(dirname "$0")/.."

missing=()
for tool in socat mbpoll; do
    command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
done
# Headless Chromium and its WebDriver for the web console's browser tests.
command -v chromium >/dev/null 2>&1 || missing+=(chromium)
command -v chromedriver >/dev/null 2>&1 || missing+=(chromium-driver)
# The container tools, with runc named so apt does not pick crun for podman.
for tool in podman runc mmdebstrap; do
    if ! command -v "$tool" >/dev/null 2>&1; then
        missing+=(podman runc mmdebstrap uidmap slirp4netns fuse-overlayfs)
        break
    fi
done
if ((${#missing[@]})); then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    echo "installing Debian packages: ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if [ -f tests/node/package-lock.json ]; then
    if [ ! -d tests/node/node_modules ] || [ tests/node/package-lock.json -nt tests/node/node_modules ]; then
        command -v npm >/dev/null || { echo "npm is needed for the node-opcua tests"; exit 1; }
        (cd tests/node && npm ci --no-audit --no-fund --loglevel=error)
        touch tests/node/node_modules
    fi
fi

# InfluxDB 1.8.10 serves the v2 write API and Flux queries influxdb-client uses;
# Debian's influxdb (1.6) does not. Built from source with Go, cached (git-ignored).
INFLUXD=.cache/bin/influxd
if [ ! -x "$INFLUXD" ]; then
    command -v go >/dev/null || export PATH="$PATH:/usr/local/go/bin"
    command -v go >/dev/null || { echo "Go is needed to build influxd 1.8.10 for the tests"; exit 1; }
    echo "building influxd 1.8.10 into .cache/bin (a few minutes, once)"
    mkdir -p .cache/bin
    GOBIN="$PWD/.cache/bin" go install -trimpath \
        -ldflags "-s -w -X main.version=1.8.10" \
        github.com/influxdata/influxdb/cmd/influxd@v1.8.10
fi

# The image's base (a Debian root filesystem, once per machine) and its locked
# dependencies stage (once per requirements.lock), so the image build in
# tests/test_container.py builds only what the code changes. Seconds when cached.
bash scripts/build-image.sh --prepare
