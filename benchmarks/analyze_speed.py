"""How long ``python -m gateway analyze`` takes, end to end, as a user runs it.

Three files: the real 46-hour test (``data/fl_thermal.csv``, target ``ch1_um``)
and two synthetic files of ``--rows`` rows (default 1 000 000: ten runs, 16
sensors, 15 s sampling, written by :func:`benchmarks.fit_speed.write_synthetic`):
one the model explains (one round, ``none``), one with a direct speed effect (1 µm per
1000 r/min) the analysis has to find (several rounds); and the first again with each
timestamp moved by up to ±0.4 s, as a polling logger writes them, which the lags must
step unevenly.
Each figure is the wall time of one CLI subprocess (load, fit, every candidate,
every round), the median of ``--repeat`` runs measured in this one process.
Prints one JSON document.

    .venv/bin/python benchmarks/analyze_speed.py [--rows 1000000] [--repeat 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from benchmarks.fit_speed import write_synthetic  # noqa: E402

LIMITS_S = {
    "fl_thermal": 10.0,
    "synthetic": 60.0,
    "synthetic_speed_effect": 60.0,
    "synthetic_jittered": 60.0,
}


def analyze_seconds(path: Path, target: str, repeat: int, out: Path) -> tuple[float, dict]:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "gateway",
                "analyze",
                str(path),
                "--model",
                "mlr",
                "--target",
                target,
                "--json",
                str(out),
                "--no-progress",
            ],
            cwd=ROOT,
            check=True,
            capture_output=True,
            text=True,
        )
        times.append(time.perf_counter() - start)
    return statistics.median(times), json.loads(out.read_text(encoding="utf-8"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        synthetic = folder / "synthetic.csv"
        write_synthetic(synthetic, args.rows)
        speed_effect = folder / "synthetic_speed_effect.csv"
        write_synthetic(speed_effect, args.rows, hidden_um_per_krpm=1.0)
        jittered = folder / "synthetic_jittered.csv"
        frame = pd.read_csv(synthetic)
        jitter = np.random.default_rng(5).uniform(-0.4, 0.4, len(frame))
        frame["time_s"] = frame["time_s"] + np.round(jitter, 2)
        frame.to_csv(jittered, index=False)
        for name, path, target in (
            ("fl_thermal", ROOT / "data" / "fl_thermal.csv", "ch1_um"),
            ("synthetic", synthetic, "error_um"),
            ("synthetic_speed_effect", speed_effect, "error_um"),
            ("synthetic_jittered", jittered, "error_um"),
        ):
            wall, payload = analyze_seconds(path, target, args.repeat, folder / f"{name}.json")
            results[name] = {
                "rows": payload["before"]["n_samples"],
                "wall_s": round(wall, 2),
                "limit_s": LIMITS_S[name],
                "within_limit": wall < LIMITS_S[name],
                "effects": [step["effect"] for step in payload["steps"]] or ["none"],
                "rmse_before_um": payload["before"]["rmse_um"],
                "rmse_after_um": payload["after"]["rmse_um"],
            }
    print(
        json.dumps(
            {
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "analyze": results,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
