"""A configuration of many machines sharing one model store: checking and start-up cost.

Generates ``--machines`` machines (default 1000; one Modbus TCP CNC each, one shared
store of the demo's 12 models, tests/test_big_config.py's layout) and measures:

- ``check_config``: ``python -m gateway check-config`` as a process, wall and CPU s;
- ``start_models``: in one process, what ``run`` does per machine before its first
  cycle (``load_config`` then ``load_bank`` for every machine), CPU s, with the
  per-process caches and with them emptied before each machine (as every machine
  re-read the shared store before);
- ``run``: ``python -m gateway run`` as a process on the machines served over Modbus
  TCP by benchmarks/poll_vs_telegraf.py's device servers (one port per machine, its
  transmitters and CNC): seconds from the process start until the loops were built
  (``built_s``), the first machine's and the last machine's first heartbeat, and the
  process's CPU seconds at the last one.

Prints one JSON document.

    .venv/bin/python benchmarks/big_config.py [--machines 1000]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.poll_vs_telegraf import Devices  # noqa: E402
from gateway.config import load_config  # noqa: E402
from gateway.live.bank import model_bank  # noqa: E402
from gateway.wiring import load_bank  # noqa: E402
from tests.test_big_config import measure_start, run_measured, write_config  # noqa: E402


def start_models_cpu_s(config: Path, cached: bool) -> float:
    started = time.process_time()
    for machine in load_config(config).machines:
        if not cached:
            model_bank._checked_files.clear()
            model_bank._sensitivities.clear()
        load_bank(machine)
    return time.process_time() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=1000)
    parser.add_argument(
        "--within-s", type=float, default=120.0, help="give up on run's start after this long"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        config = write_config(Path(folder), args.machines)
        started = time.perf_counter()
        code, out, cpu_s = run_measured("check-config", "--config", config)
        wall_s = time.perf_counter() - started
        if code != 0:
            raise SystemExit(out[-2000:])
        result = {
            "machines": args.machines,
            "load_average_1min": round(os.getloadavg()[0], 1),
            "check_config": {"wall_s": round(wall_s, 2), "cpu_s": round(cpu_s, 2)},
            "start_models_cpu_s": {
                "cached": round(start_models_cpu_s(config, cached=True), 2),
                "store_read_per_machine": round(start_models_cpu_s(config, cached=False), 2),
            },
        }
        result["run"] = run_start(args.machines, args.within_s)
    print(json.dumps(result, indent=2))


def run_start(machines: int, within_s: float) -> dict[str, object]:
    """``run`` on ``machines`` served machines: when each first cycled (s since start)."""
    devices = Devices(machines)
    try:
        with tempfile.TemporaryDirectory() as folder:
            config = write_config(Path(folder), machines, devices.ports)
            start = measure_start(config, machines, Path(folder) / "state", within_s)
    finally:
        devices.close()
    figures = {k: round(v, 2) if isinstance(v, float) else v for k, v in asdict(start).items()}
    return {**figures, "load_average_1min": round(os.getloadavg()[0], 1)}


if __name__ == "__main__":
    main()
