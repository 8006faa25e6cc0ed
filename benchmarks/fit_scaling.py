"""How ``fit`` and ``analyze`` grow with the number of runs: wall time and peak memory.

Records 48 simulated production runs once (``simulate --record``, 40 s sampling,
the hidden thermal lag on, each run cut to its first 6 h), with 24 temperature
sensors: the simulated machine's T1..T9 plus T10..T24 added through ``--params``
(each a mix of two thermal nodes with its own lag and offset, seeded), and the
ambient column. The first 6, 12, 24 and 48 runs are then fitted and analysed,
each command a process of its own as an operator runs it; wall time is measured
around the process and peak memory is its maximum resident set (``wait4``).

Prints one JSON document: every figure, and per method and command the growth
exponent b of wall ∝ runs^b and of CPU ∝ runs^b (least squares over all sizes, and
between the two largest). Figures are from one run on this machine, not a test.

    .venv/bin/python benchmarks/fit_scaling.py [--runs 6,12,24,48] [--methods ...]
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
import yaml

ROOT = Path(__file__).resolve().parent.parent
PYTHON = sys.executable
NODES = ("bearing", "shaft", "motor", "headstock", "column")
RUN_HOURS = 6.0
SAMPLE_S = 40.0


def extra_sensors(first: int, last: int, seed: int = 7) -> dict[str, dict[str, object]]:
    """Sensors T<first>..T<last>: each reads two thermal nodes through its own lag."""
    rng = np.random.default_rng(seed)
    sensors: dict[str, dict[str, object]] = {}
    for i in range(first, last + 1):
        a, b = (str(node) for node in rng.choice(NODES, 2, replace=False))
        share = round(float(rng.uniform(0.5, 0.95)), 2)
        sensors[f"T{i}"] = {
            "location": f"{a} (added for the benchmark)",
            "mix": {a: share, b: round(1.0 - share, 2)},
            "lag_s": int(rng.integers(20, 120)),
            "offset_C": round(float(rng.normal(0.0, 0.2)), 2),
        }
    return sensors


def record(folder: Path, runs: int) -> Path:
    """The recording of ``runs`` production runs, 6 h each, 24 sensors."""
    params = folder / "params.yaml"
    params.write_text(yaml.safe_dump({"sensors": extra_sensors(10, 24)}))
    full = folder / "full.csv"
    programs = [arg for i in range(1, runs + 1) for arg in ("--program", f"production-{i}")]
    options = ["--effect", "thermal_lag", "--sample-s", str(SAMPLE_S), "--params", str(params)]
    subprocess.run(
        [PYTHON, "-m", "gateway", "simulate", "--record", str(full), *programs, *options],
        cwd=ROOT,
        check=True,
        stdout=subprocess.DEVNULL,
    )
    data = pd.read_csv(full)
    data = data[data["time_s"] < RUN_HOURS * 3600.0]
    data.to_csv(full, index=False)
    return full


def first_runs(full: Path, runs: int, folder: Path) -> Path:
    data = pd.read_csv(full)
    keep = list(dict.fromkeys(data["run"]))[:runs]
    path = folder / f"runs{runs}.csv"
    data[data["run"].isin(keep)].to_csv(path, index=False)
    return path


def measure(args: list[str], json_path: Path) -> dict[str, object]:
    """Wall seconds, peak resident MB and the held-out pooled RMSE of one CLI process."""
    start = time.perf_counter()
    process = subprocess.Popen(
        [PYTHON, "-m", "gateway", *args, "--json", str(json_path)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, status, usage = os.wait4(process.pid, 0)
    wall_s = time.perf_counter() - start
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed: {process.stderr.read().decode()[-2000:]}")
    return {
        "wall_s": round(wall_s, 1),
        "peak_MB": round(usage.ru_maxrss / 1024.0, 1),
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
        "rmse_um": held_out_rmse(json.loads(json_path.read_text())),
    }


def held_out_rmse(document: dict) -> float | None:
    """The pooled held-out RMSE the command reports (fit: regime ``all``; analyze: after)."""
    validation = document.get("validations", {}).get("all")
    if validation is not None:
        return round(validation["pooled"]["rmse_um"], 3)
    after = document.get("after")
    if isinstance(after, dict):
        return round(float(after["rmse_um"]), 3)
    return None


def growth(runs: list[int], wall_s: list[float]) -> dict[str, float]:
    """Exponent b of wall ∝ runs^b: fitted over every size, and between the two largest."""
    slope = np.polyfit(np.log(runs), np.log(wall_s), 1)[0]
    last = np.log(wall_s[-1] / wall_s[-2]) / np.log(runs[-1] / runs[-2])
    return {"all_sizes": round(float(slope), 2), "two_largest": round(float(last), 2)}


def commands(data: Path, method: str, store: Path) -> dict[str, list[str]]:
    return {
        "fit": ["fit", str(data), "--method", method, "--store", str(store), "--no-progress"],
        "analyze": ["analyze", str(data), "--model", method, "--no-progress"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", default="6,12,24,48")
    parser.add_argument("--methods", default="mlr,ridge,pls,lag-ridge")
    parser.add_argument("--commands", default="fit,analyze")
    parser.add_argument("--folder", type=Path, help="Keep the recordings here (else a temp dir).")
    args = parser.parse_args()
    sizes = [int(r) for r in args.runs.split(",")]
    with tempfile.TemporaryDirectory() as temp:
        folder = args.folder or Path(temp)
        folder.mkdir(parents=True, exist_ok=True)
        full = record(folder, max(sizes))
        results: dict[str, dict[str, dict[str, object]]] = {}
        for runs in sizes:
            data = first_runs(full, runs, folder)
            for method in args.methods.split(","):
                for name, argv in commands(data, method, folder / "store").items():
                    if name not in args.commands.split(","):
                        continue
                    figures = measure(argv, folder / f"{name}-{method}-{runs}.json")
                    results.setdefault(name, {}).setdefault(method, {})[str(runs)] = figures
                    print(name, method, runs, figures, file=sys.stderr, flush=True)
    exponents = {
        f"{name} {figure}": {
            method: growth(sizes, [by_runs[str(r)][figure] for r in sizes])
            for method, by_runs in by_method.items()
        }
        for name, by_method in results.items()
        for figure in ("wall_s", "cpu_s")
    }
    print(
        json.dumps(
            {
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "load_average_at_end": os.getloadavg(),
                "recording": {"hours_per_run": RUN_HOURS, "sample_s": SAMPLE_S, "sensors": 24},
                "results": results,
                "growth_exponent": exponents,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
