#!/usr/bin/env bash
# System packages the tests need, installed only when missing:
#   socat  (a serial pty pair for Modbus RTU without hardware)
#   mbpoll (an independent libmodbus-based Modbus master)
#   libfaketime (a process's wall clock stepped by a test: tests/test_clock_step.py)
#   chromium, chromium-driver (headless browser tests of the web console)
#   node-opcua (an independent OPC UA client, pinned in tests/node/package-lock.json)
#   influxd 2.7.12 (a real time-series server; built once with Go and Rust into .cache/bin)
#   podman, runc, mmdebstrap (the gateway image is built and run: tests/test_container.py),
#   and the image's base and locked dependencies (scripts/build-image.sh --prepare)
set -euo pipefail
cd "$(dirname "$0")/.."

missing=()
for tool in socat mbpoll; do
    command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
done
[ -f /usr/lib/x86_64-linux-gnu/faketime/libfaketimeMT.so.1 ] || missing+=(libfaketime)
# Mosquitto 2 and its clients: the broker the Sparkplug B tests start themselves.
command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || missing+=(mosquitto mosquitto-clients)
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

# InfluxDB 2.7.12, the version deploy/docker-compose.yml ships, as a real server for the
# tests (tests/influx_server.py). Built from source with Go and Rust into .cache/bin
# (git-ignored): about 12 minutes once on two cores, then nothing.
if [ ! -x .cache/bin/influxd2 ]; then
    mkdir -p .cache
    echo "building influxd 2.7.12 into .cache/bin (about 12 minutes, once; log: .cache/influxd2-build.log)"
    bash scripts/build-influxd2.sh >.cache/influxd2-build.log 2>&1 || {
        tail -n 40 .cache/influxd2-build.log
        echo "building influxd 2.7.12 failed; the whole log: .cache/influxd2-build.log"
        exit 1
    }
fi

# The image's base (a Debian root filesystem, once per machine) and its locked
# dependencies stage (once per requirements.lock), so the image build in
# tests/test_container.py builds only what the code changes. Seconds when cached.
bash scripts/build-image.sh --prepare
