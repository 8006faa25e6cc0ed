"""The residual monitor's cost: per probe, and its analysis of 30 days of history at 1 Hz.

1. ``per_probe``: :meth:`ResidualMonitor.observe` (both sequential tests, the
   window regression at every probe) and the whole sink per cycle
   (:class:`gateway.live.proposal_monitor.MonitorSink`: history append, shadow filter, tests),
   on cycles with and without a probe.
2. ``analysis``: the background analysis of 30 days of logged history at 1 Hz
   (2 592 000 cycles, a probe every 300 s: 8640 probe rows), as the monitor runs
   it: history saved, a separate process started, loaded, analysed. The history
   is the simulated machine with a hidden ``thermal_lag`` run in-process at a
   15 s cycle (``gateway/demo/monitor_phase.py``), brought to 1 Hz by linear
   interpolation of the temperatures (the speed held, each probe on its own row).
3. ``cycle_latency``: while that analysis runs, a real compensation loop
   (Modbus TCP transmitters and CNC, the simulator in its own process) cycles
   against the simulator, and each ``run_cycle`` is timed; the same before the
   analysis starts, as the baseline.

Prints one JSON document.

    .venv/bin/python benchmarks/monitor_cost.py [--days 30] [--probes 5000]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import loop_latency  # noqa: E402

from drivers.clock import WallClock  # noqa: E402
from gateway.demo.compensate import fit_models, write_training_data  # noqa: E402
from gateway.demo.monitor_phase import SENSORS, InProcessPlant, programme_days  # noqa: E402
from gateway.live.proposal_monitor import MonitorSink, run_analysis_job  # noqa: E402
from models.analysis.history import History  # noqa: E402
from models.online.residual_monitor import MonitorParams, ProbeInnovation, ResidualMonitor  # noqa: E402
from tests.records import written_record  # noqa: E402

PROBE_PERIOD_S = 300.0


def per_probe(probes: int) -> dict[str, float]:
    rng = np.random.default_rng(0)
    monitor = ResidualMonitor(MonitorParams(false_alarms_per_month=1e-6))
    rows = [
        ProbeInnovation(i * PROBE_PERIOD_S, 0.5 * rng.standard_normal(), 0.5, 3000.0, 500.0, 60.0)
        for i in range(probes)
    ]
    start = time.perf_counter()
    for row in rows:
        monitor.observe(row)
    observe_us = (time.perf_counter() - start) / probes * 1e6

    sink = MonitorSink("bench", SENSORS, MonitorParams(false_alarms_per_month=1e-6), cycle_s=1.0)
    times = {True: [], False: []}
    for i in range(probes * 20):
        probe = i % 20 == 19
        record = written_record(
            "bench",
            float(i),
            {s: 25.0 + 0.001 * i for s in SENSORS},
            5.0,
            speed_rpm=3000.0,
            probe_error_um=float(0.3 * rng.standard_normal()) if probe else None,
        )
        start = time.perf_counter()
        sink(record)
        times[probe].append(time.perf_counter() - start)
    return {
        "observe_us_per_probe": round(observe_us, 1),
        "sink_us_per_probe_cycle": round(statistics.median(times[True]) * 1e6, 1),
        "sink_us_per_other_cycle": round(statistics.median(times[False]) * 1e6, 1),
        "probes": probes,
    }


def history_at_1hz(store: Path, days: float) -> History:
    """``days`` of the thermal_lag machine at a 15 s cycle, interpolated to 1 Hz."""
    plant = InProcessPlant(store, programme_days(7, int(np.ceil(days)) + 1), ("thermal_lag",))
    sink = MonitorSink("bench", SENSORS, MonitorParams(false_alarms_per_month=1e-6), cycle_s=15.0)
    plant.sinks.append(sink)
    plant.run_for(days * 86400.0)
    coarse = sink.history.snapshot()
    time_s = np.arange(coarse.time_s[0], coarse.time_s[-1] + 1.0, 1.0)
    temps = np.column_stack(
        [np.interp(time_s, coarse.time_s, coarse.temperatures_C[:, j]) for j in range(len(SENSORS))]
    )
    index = np.searchsorted(coarse.time_s, time_s, side="right") - 1
    speed = coarse.speed_rpm[np.clip(index, 0, None)]
    error = np.full(time_s.size, np.nan)
    probe = coarse.probe_rows
    error[np.searchsorted(time_s, coarse.time_s[probe])] = coarse.error_um[probe]
    return History(time_s, speed, SENSORS, temps, error)


async def cycles_while(section, future, baseline_cycles: int) -> dict[str, object]:
    """run_cycle times before ``future`` is started (baseline) and while it runs."""
    clock = WallClock()
    loop = loop_latency.make_loop(section, clock)
    before, during = [], []
    try:
        for _ in range(20):
            await loop.run_cycle()
        for _ in range(baseline_cycles):
            await asyncio.sleep(0.1)
            start = time.perf_counter()
            await loop.run_cycle()
            before.append(time.perf_counter() - start)
        job, submitted = future(), time.perf_counter()
        while not job.done():
            await asyncio.sleep(0.1)
            start = time.perf_counter()
            await loop.run_cycle()
            during.append(time.perf_counter() - start)
        analysis_s = time.perf_counter() - submitted
    finally:
        await loop.close()
    return {
        "analysis_wall_s": round(analysis_s, 1),
        "result": job.result(),
        "before": loop_latency.summary_ms(before) | {"max_ms": round(max(before) * 1e3, 2)},
        "during": loop_latency.summary_ms(during) | {"max_ms": round(max(during) * 1e3, 2)},
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--days", type=float, default=30.0)
    parser.add_argument("--probes", type=int, default=5000)
    args = parser.parse_args()
    out: dict[str, object] = {"per_probe": per_probe(args.probes)}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        write_training_data(folder / "training.csv", seed=1)
        fit_models(folder / "training.csv", folder / "models", "bench")
        started = time.perf_counter()
        history = history_at_1hz(folder / "models", args.days)
        build_s = time.perf_counter() - started
        path = folder / "history.npz"
        history.save(str(path))
        ports = {"bus": loop_latency.free_port(), "opcua": loop_latency.free_port()}
        ports["modbus"] = loop_latency.free_port()
        simulator = loop_latency.start_simulator(folder, ports)
        executor = ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn"))
        try:
            section = loop_latency.machine(folder / "models", ports, "modbus")
            measured = asyncio.run(
                cycles_while(
                    section,
                    lambda: executor.submit(run_analysis_job, str(path), "mlr", None, "bench"),
                    baseline_cycles=300,
                )
            )
        finally:
            executor.shutdown()
            simulator.terminate()
            simulator.wait(timeout=30)
    result = measured.pop("result")
    out["analysis"] = {
        "days": args.days,
        "rows": history.n_samples,
        "probe_rows": int(history.probe_rows.sum()),
        "history_build_s": round(build_s, 1),
        "wall_s": measured.pop("analysis_wall_s"),
        "effect": result["effect"],
        "effects": result["effects"],
        "before_rmse_um": round(result["before"]["rmse_um"], 3),
        "after_rmse_um": round(result["after"]["rmse_um"], 3),
    }
    out["cycle_latency"] = measured
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
