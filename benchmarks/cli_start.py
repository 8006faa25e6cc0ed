"""How fast the command line starts, and what it imports to do so.

The container's health check (``python -m gateway.outputs.heartbeat``, see the Dockerfile's
HEALTHCHECK) runs every 15 s and an operator types ``--help``: neither should pay
for numpy, scipy, pandas, matplotlib, sklearn or the protocol libraries. Each
command runs as a fresh subprocess ``--repeats`` times; the median wall time and
the heavy top-level packages seen by ``-X importtime`` are printed as JSON.

    .venv/bin/python benchmarks/cli_start.py [--repeats 10]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HEAVY = (
    "numpy",
    "scipy",
    "pandas",
    "matplotlib",
    "sklearn",
    "asyncua",
    "pymodbus",
    "influxdb_client",
    "pydantic",
)
COMMANDS = {
    "gateway --help": ["-m", "gateway", "--help"],
    "gateway check-config --help": ["-m", "gateway", "check-config", "--help"],
    "gateway run --help": ["-m", "gateway", "run", "--help"],
    "gateway.outputs.heartbeat --help": ["-m", "gateway.outputs.heartbeat", "--help"],
}


def wall_time_s(args: list[str]) -> float:
    started = time.perf_counter()
    subprocess.run([sys.executable, *args], cwd=ROOT, check=True, capture_output=True)
    return time.perf_counter() - started


def heavy_imports(args: list[str]) -> list[str]:
    """Top-level heavy packages named in the ``-X importtime`` log (it goes to stderr)."""
    done = subprocess.run(
        [sys.executable, "-X", "importtime", *args],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    )
    seen = set()
    for line in done.stderr.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        module = line.rsplit("|", 1)[1].strip()
        if module.split(".")[0] in HEAVY:
            seen.add(module.split(".")[0])
    return sorted(seen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    options = parser.parse_args()
    results = {}
    for name, args in COMMANDS.items():
        times = [wall_time_s(args) for _ in range(options.repeats)]
        results[name] = {
            "median_s": round(statistics.median(times), 3),
            "min_s": round(min(times), 3),
            "max_s": round(max(times), 3),
            "heavy_imports": heavy_imports(args),
        }
    print(json.dumps({"python": sys.version.split()[0], "repeats": options.repeats, **results}))


if __name__ == "__main__":
    main()
