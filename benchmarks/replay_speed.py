"""How long ``python -m gateway replay`` takes on the real 46-hour test, end to end.

One CLI subprocess per channel (ch1_um, ch3_um, ch5_um) with probes every 30, 60
and 120 min, as the README's table is made: load, three nested leave-one-cycle-out
replays (base choice, filter choice, the held-out replay), table and JSON. Prints
one JSON document with the wall time and the figures of each channel.

    .venv/bin/python benchmarks/replay_speed.py
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CHANNELS = ("ch1_um", "ch3_um", "ch5_um")
INTERVALS_MIN = ("30", "60", "120")
LIMIT_S = 60.0  # per channel: seconds, not minutes


def main() -> None:
    results = {}
    with tempfile.TemporaryDirectory() as folder:
        for channel in CHANNELS:
            out = Path(folder) / f"{channel}.json"
            command = [sys.executable, "-m", "gateway", "replay", "data/fl_thermal.csv"]
            command += ["--model", "mlr", "--base", "lagged"]
            command += ["--target", channel, "--json", str(out)]
            for interval in INTERVALS_MIN:
                command += ["--probe-interval-min", interval]
            start = time.perf_counter()
            subprocess.run(command, cwd=ROOT, check=True, capture_output=True)
            wall_s = time.perf_counter() - start
            replay = json.loads(out.read_text(encoding="utf-8"))
            results[channel] = {
                "wall_s": round(wall_s, 2),
                "within_limit": wall_s <= LIMIT_S,
                "offline_rmse_um": round(replay["offline"]["rmse_um"], 2),
                "online_rmse_um": {
                    f"{row['probe_interval_min']:g} min": round(row["rmse_um"], 2)
                    for row in replay["online"]
                },
            }
    print(
        json.dumps(
            {
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "limit_s": LIMIT_S,
                "channels": results,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
