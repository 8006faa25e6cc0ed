"""Peak memory of ``fit`` and ``analyze`` on a 220 MB measured-run CSV (2.66 M rows).

The deploy notes call a 2 GB edge box plenty, so each command must stay under
1 GB peak resident memory on a file of this size. The file is written by
:func:`write_large_csv` in the layout and number format of the simulator's
recorder (``run,time_s,speed_rpm,T1…T9,ambient_C,error_um``; 1 s sampling,
temperatures at 0.1 °C, the error at 0.01 µm), ten runs. Each command runs as a
user runs it, one ``python -m gateway`` subprocess, and its peak RSS is the
child's own ``ru_maxrss`` from :func:`os.wait4`. Prints one JSON document.

Measured on this 2-core machine (214 MB, 2 660 000 rows, 9 sensors, ten runs):
``fit`` 2482 MB before the column-wise reader and the copy removals, 784 MB
after; ``analyze`` 2809 MB before, 914 MB after (limit 1024 MB).

    .venv/bin/python benchmarks/memory_large_csv.py [--rows 2660000] [--command fit analyze]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.signal import lfilter

ROOT = Path(__file__).resolve().parent.parent
LIMIT_MB = 1024.0
N_SENSORS = 9
N_RUNS = 10
REST_S = 600
SPEEDS_RPM = (0, 2000, 4000, 6000, 8000)


def write_large_csv(path: Path, rows: int, seed: int = 0) -> None:
    """``rows`` samples in ten runs, one run at a time (the writer itself stays small).

    Each run opens with 10 min at rest, then holds a random speed for 30 min
    at a time; the sensors are first-order lags (10…50 min) of a speed-driven
    heat input, and the error is a fixed mix of three sensor rises plus 0.25 µm
    of probe noise, so ``analyze`` finds nothing to add (one round).
    """
    rng = np.random.default_rng(seed)
    per_run = rows // N_RUNS
    header = ["run", "time_s", "speed_rpm", *(f"T{i + 1}" for i in range(N_SENSORS))]
    header += ["ambient_C", "error_um"]
    with path.open("w", newline="", encoding="utf-8") as out:
        out.write(",".join(header) + "\n")
        for run in range(N_RUNS):
            n = per_run + (rows - per_run * N_RUNS if run == N_RUNS - 1 else 0)
            time_s = np.arange(n, dtype=np.int64)
            steps = rng.choice(SPEEDS_RPM, size=n // 1800 + 1)
            speed = np.repeat(steps, 1800)[:n]
            speed[time_s < REST_S] = 0
            drive = (speed / 8000.0) ** 1.5
            ambient = 20.0 + 1.5 * np.sin(2 * np.pi * time_s / 86_400.0 + run)
            columns: dict[str, np.ndarray] = {
                "run": np.full(n, f"production-{run:02d}"),
                "time_s": time_s,
                "speed_rpm": speed,
            }
            rises = []
            for i in range(N_SENSORS):
                a = np.exp(-1.0 / (600.0 + 300.0 * i))
                rises.append(12.0 * lfilter([1 - a], [1, -a], drive))
                reading = ambient + rises[-1] + rng.normal(0, 0.03, n)
                columns[f"T{i + 1}"] = np.round(reading, 1)
            columns["ambient_C"] = np.round(ambient + rng.normal(0, 0.03, n), 1)
            error = 1.8 * rises[0] + 0.9 * rises[4] - 0.6 * rises[8] + rng.normal(0, 0.25, n)
            columns["error_um"] = np.round(error, 2)
            pd.DataFrame(columns).to_csv(out, header=False, index=False, lineterminator="\n")


def measure(args: list[str], workdir: Path, name: str) -> dict[str, object]:
    """Run one gateway command; its own peak RSS (os.wait4), wall time and exit status."""
    stdout = (workdir / f"{name}.out").open("w")
    stderr = (workdir / f"{name}.err").open("w")
    start = time.perf_counter()
    with stdout, stderr:
        process = subprocess.Popen(
            [sys.executable, "-m", "gateway", *args], cwd=ROOT, stdout=stdout, stderr=stderr
        )
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
    wall_s = time.perf_counter() - start
    peak_mb = usage.ru_maxrss / 1024.0  # Linux reports kilobytes
    result: dict[str, object] = {
        "exit_status": process.returncode,
        "peak_rss_mb": round(peak_mb, 1),
        "limit_mb": LIMIT_MB,
        "within_limit": process.returncode == 0 and peak_mb < LIMIT_MB,
        "wall_s": round(wall_s, 1),
    }
    if process.returncode != 0:
        result["stderr_tail"] = (workdir / f"{name}.err").read_text(encoding="utf-8")[-2000:]
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=2_660_000)
    parser.add_argument("--command", nargs="+", choices=("fit", "analyze"), default=None)
    parser.add_argument(
        "--data", type=Path, help="Use this file if it exists, else write it there (and keep it)."
    )
    args = parser.parse_args()
    commands = args.command or ["fit", "analyze"]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        data = args.data or folder / "large.csv"
        start = time.perf_counter()
        if not data.exists():
            write_large_csv(data, args.rows)
        generated_s = time.perf_counter() - start
        runs = {
            "fit": ["fit", data, "--method", "mlr", "--store", folder / "store", "--no-progress"],
            "analyze": [
                "analyze",
                data,
                "--model",
                "mlr",
                "--json",
                folder / "analyze.json",
                "--no-progress",
            ],
        }
        results = {name: measure([str(a) for a in runs[name]], folder, name) for name in commands}
        size_mb = data.stat().st_size / 1e6
    print(
        json.dumps(
            {
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "file": {
                    "rows": sum(1 for _ in data.open("rb")) - 1 if args.data else args.rows,
                    "size_mb": round(size_mb, 1),
                    "generate_s": round(generated_s, 1),
                },
                "peak_rss": results,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
