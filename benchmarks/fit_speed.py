"""How long each method's fit takes: on the real 46-hour test and on 1 000 000 rows.

Prints one JSON document. Loading the CSV is timed separately from fitting, and
every figure is the median of ``--repeat`` runs measured in this one process.

    .venv/bin/python benchmarks/fit_speed.py [--rows 1000000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.signal import lfilter

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from models.data.dataset import load_runs  # noqa: E402
from models.data.features import prepare  # noqa: E402
from models.estimators.registry import METHODS, make_model  # noqa: E402

N_SENSORS = 16


def seconds(action: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def write_synthetic(path: Path, rows: int, seed: int = 0, hidden_um_per_krpm: float = 0.0) -> None:
    """Ten runs at 15 s sampling; sensors are first-order lags of a speed-driven heat input.

    ``hidden_um_per_krpm`` adds an error term no temperature explains: growth
    proportional to the speed itself (centrifugal), so ``analyze`` has an
    effect to find and goes through more than one round.
    """
    rng = np.random.default_rng(seed)
    per_run = rows // 10
    run = np.repeat([f"r{i:02d}" for i in range(10)], per_run)
    n = run.size
    time_s = np.tile(np.arange(per_run) * 15.0, 10)
    steps = rng.choice([0, 1500, 3000, 4500, 6000], size=n // 480 + 1)
    speed = np.repeat(steps, 480)[:n].astype(float)
    drive = (speed / 6000.0) ** 1.5
    columns: dict[str, np.ndarray] = {"run": run, "time_s": time_s, "speed_rpm": speed}
    temps = []
    for i in range(N_SENSORS):
        a = np.exp(-15.0 / (600.0 + 300.0 * i))
        temps.append(20.0 + 15.0 * lfilter([1 - a], [1, -a], drive) + rng.normal(0, 0.02, n))
        columns[f"T{i + 1}"] = temps[-1]
    error_um = 3.0 * (temps[0] - 20) - 1.5 * (temps[8] - 20) + rng.normal(0, 0.5, n)
    error_um += hidden_um_per_krpm * speed / 1000.0
    columns["error_um"] = error_um
    pd.DataFrame(columns).to_csv(path, index=False, float_format="%.4f")


def bench_file(path: Path, target: str, repeat: int) -> dict[str, object]:
    load_s = seconds(lambda: load_runs(path, target=target), 1)
    prepared = prepare(load_runs(path, target=target))
    fits = {
        method: round(
            seconds(lambda m=method: make_model(m).fit(prepared.inputs, prepared.error_um), repeat),
            4,
        )
        for method in sorted(METHODS)
    }
    return {
        "file": path.name,
        "rows": prepared.data.n_samples,
        "sensors": len(prepared.inputs.sensors),
        "load_s": round(load_s, 3),
        "fit_s": fits,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    result: dict[str, object] = {
        "machine": {"python": platform.python_version(), "cpu_count": __import__("os").cpu_count()},
        "fl_thermal": bench_file(ROOT / "data" / "fl_thermal.csv", "ch5_um", args.repeat),
    }
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"synthetic_{args.rows}.csv"
        start = time.perf_counter()
        write_synthetic(path, args.rows)
        generated_s = time.perf_counter() - start
        synthetic = bench_file(path, "error_um", args.repeat)
        synthetic["generate_s"] = round(generated_s, 2)
        result["synthetic"] = synthetic
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
