#!/usr/bin/env bash
# System packages the tests need, installed only when missing:
#   socat  (a serial pty pair for Modbus RTU without hardware)
#   mbpoll (an independent libmodbus-based Modbus master)
#   node-opcua (an independent OPC UA client, pinned in tests/node/package-lock.json)
set -euo pipefail
cd "$(dirname "$0")/.."

missing=()
for tool in socat mbpoll; do
    command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
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
