"""Availability and accuracy of the compensation with one faulty sensor; prints JSON.

The simulated machine serves its transmitters and CNC over Modbus TCP on
loopback; the gateway's loop compensates it on a manual clock (30 s cycles)
with the store the demo fits. The busy-day programme of
tests/test_plausibility_loop.py runs once without a fault, then once per
sensor and fault: a +3 °C offset and a 20 °C/h drift, each from an hour into
the programme for 150 cycles (75 min). Per run, over those 150 cycles:

- ``predicting_pct``: cycles with a prediction (the rest hold, then ramp to 0);
- ``held``: every sensor held at some cycle, and the largest number at once;
- ``rmse_um`` / ``peak_um``: the error left at the tool (compensated), against
  the fault-free run's over the same cycles: the accuracy cost of the fallback
  model and of the cycles before the flag.

Run: ``.venv/bin/python benchmarks/sensor_fault_availability.py`` (about 2 min).
"""

from __future__ import annotations

import asyncio
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from simulator.closed_loop import ClosedLoop
from simulator.faults import SensorFault
from tests import gateway_rig as rig
from tests.test_plausibility_loop import (
    BUSY_PROGRAM,
    CYCLE_S,
    FAULT_AT_S,
    run_machine,
)

CYCLES = 150
SENSORS = [f"T{i}" for i in range(1, 10)]
FAULTS = {"offset +3 °C": ("offset", 3.0), "drift 20 °C/h": ("drift", 20.0)}


def window(closed: ClosedLoop) -> tuple[list, np.ndarray]:
    """The records and compensated errors (µm) of the cycles after the fault start."""
    start = closed.start_s + FAULT_AT_S  # type: ignore[attr-defined]
    keep = [k for k, r in enumerate(closed.trace.records) if r.time_s > start]
    records = [closed.trace.records[k] for k in keep]
    return records, np.asarray(closed.trace.compensated_um)[keep]


def figures(closed: ClosedLoop) -> dict[str, object]:
    records, error_um = window(closed)
    held = sorted({s for r in records for s, why in r.quality_reasons.items() if "implaus" in why})
    at_once = max(sum(q == "bad" for q in r.quality.values()) for r in records)
    predicting = sum(r.predicted_um is not None for r in records)
    return {
        "cycles": len(records),
        "predicting_pct": round(100.0 * predicting / len(records), 1),
        "held": held,
        "most_held_at_once": at_once,
        "rmse_um": round(float(np.sqrt(np.mean(error_um**2))), 2),
        "peak_um": round(float(np.max(np.abs(error_um))), 2),
    }


def main() -> None:
    seconds = FAULT_AT_S + CYCLES * CYCLE_S
    with tempfile.TemporaryDirectory() as folder:
        store = rig.fit_store(Path(folder))
        clean = figures(asyncio.run(run_machine(store, BUSY_PROGRAM, seconds)))
        runs: dict[str, dict[str, object]] = {}
        for name, (kind, magnitude_C) in FAULTS.items():
            for sensor in SENSORS:
                fault = SensorFault(sensor, kind, start_s=FAULT_AT_S, magnitude_C=magnitude_C)
                closed = asyncio.run(run_machine(store, BUSY_PROGRAM, seconds, fault))
                runs[f"{name} on {sensor}"] = figures(closed)
    worst_pct = min(float(f["predicting_pct"]) for f in runs.values())  # type: ignore[arg-type]
    print(
        json.dumps(
            {
                "fault_free": clean,
                "faulted": runs,
                "lowest_predicting_pct": worst_pct,
                "largest_rmse_um": max(float(f["rmse_um"]) for f in runs.values()),  # type: ignore[arg-type]
                "largest_peak_um": max(float(f["peak_um"]) for f in runs.values()),  # type: ignore[arg-type]
            },
            indent=2,
            ensure_ascii=False,
        )
    )


if __name__ == "__main__":
    main()
