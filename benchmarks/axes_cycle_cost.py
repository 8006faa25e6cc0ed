"""CPU per machine-cycle of the compensation loop with one axis and with three; prints JSON.

One simulated machine in its own process (pinned to the other core when there are
two) serves Modbus TCP transmitters and the CNC (Modbus TCP or OPC UA), as in
``loop_latency.py``. This process, pinned to one core, runs two gateways' loops of
that machine, one after the other in alternating blocks of ``--block`` cycles (so a
slow spell of the shared machine falls on both), the same number of cycles each:

- ``one_axis``: today's single-axis form, Z written to #500, its models only;
- ``three_axes``: ``compensation.axes`` Z (#500, ``error_um``), X (#502, ``x_um``),
  Y (#504, ``y_um``), each with its own models from one store.

Each measured cycle is ``MachineLoop.run_cycle``: read both transmitter modules and
the spindle speed, check, select the regime once, predict and write every axis, read
each write back. Only cycles on which every axis wrote count (deadband 0, slew and
rate limits that never bind, sensor noise σ 0.2 °C so the values change each cycle,
the plausibility rules' thresholds out of the way of that noise).
The cost is this process's CPU time (``time.process_time``) across the cycle, not the
wall time (which is mostly waiting on the simulator); ``ratio`` is the median CPU of a
three-axis cycle over that of a one-axis cycle (target ≤ 1.5). ``requests_per_cycle``
counts the requests this process put on the wire per measured cycle (the transmitters'
Modbus TCP reads and every CNC request), counted where each driver sends one.

    .venv/bin/python benchmarks/axes_cycle_cost.py [--cycles 300] [--cnc modbus|opcua]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from loop_latency import PACE_S, free_port  # noqa: E402
from loop_latency import start_simulator as simulator_at  # noqa: E402

from drivers.clock import ManualClock  # noqa: E402
from gateway.config import MachineSection, QualitySection, SensorSection  # noqa: E402
from gateway.demo.compensate import (  # noqa: E402
    axis_targets,
    fit_models,
    machine_config,
    write_training_data,
)
from gateway.live.loop import MachineLoop  # noqa: E402
from gateway.wiring import build_buses, build_cnc, load_bank  # noqa: E402

THREE_AXES = ("Z", "X", "Y")


class RequestCounter:
    """Counts every request this process sends: each Modbus TCP request
    (``TcpTransactions._send``, transmitters and CNC) and each OPC UA service request."""

    def __init__(self) -> None:
        self.sent = 0
        from asyncua.client.ua_client import UASocketProtocol

        from drivers.modbus_tcp import TcpTransactions

        for cls, name in ((TcpTransactions, "_send"), (UASocketProtocol, "_send_request")):
            setattr(cls, name, self._counted(getattr(cls, name)))

    def _counted(self, send: Any) -> Any:
        def counted(*args: Any, **kwargs: Any) -> Any:
            self.sent += 1
            return send(*args, **kwargs)

        return counted


REQUESTS: RequestCounter | None = None
WARM_UP_CYCLES = 20  # quality needs 3 good checks; the first write starts each policy


def start_simulator(folder: Path, ports: dict[str, int]) -> subprocess.Popen[bytes]:
    """The simulated machine (:func:`loop_latency.start_simulator`) with its clock at ×400:
    the sensors' noise is drawn per 5 s of machine time, so every 30 ms cycle meets new
    readings (and a new compensation to write)."""
    return simulator_at(folder, ports, speedup=400)


def section(store: Path, ports: dict[str, int], cnc: str, axes: Sequence[str]) -> MachineSection:
    """The machine at the simulator, every cycle writing every axis."""
    link = (
        {"opcua": {"endpoint": f"opc.tcp://127.0.0.1:{ports['opcua']}/cnc", "timeout_s": 2.0}}
        if cnc == "opcua"
        else {"modbus": {"host": "127.0.0.1", "port": ports["modbus"], "timeout_s": 1.0}}
    )
    built = machine_config(
        store,
        transmitters=[
            {
                "name": "bus1",
                "tcp": {"host": "127.0.0.1", "port": ports["bus"]},
                "timeout_s": 0.5,
                "devices": [
                    {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
                    {"device_id": 2, "channels": ["T9", None]},
                ],
            }
        ],
        cnc=link,
        cycle_s=1.0,
        axes=axes,
    )
    # Copied past the checks, as loop_latency.py does: a slew limit that never binds.
    always = {"deadband_um": 0.0, "slew_um_per_min": 1e6}
    comp = built.compensation
    if comp.axes is None:
        comp = comp.model_copy(update=always)
    else:
        axes = {name: a.model_copy(update=always) for name, a in comp.axes.items()}
        comp = comp.model_copy(update={"axes": axes})
    sensors = {name: SensorSection(max_rate_C_per_s=1e6) for name in built.sensor_names}
    # Noisy sensors on 30 ms cycles: the plausibility rules would hold them (their
    # work is still done every cycle; only the verdict changes).
    loose = QualitySection(
        plausibility_sigma=1e6, max_prediction_rate_um_per_s=1e6, prediction_noise_um=1e6
    )
    update = {"compensation": comp, "sensors": sensors, "plausibility": loose}
    return built.model_copy(update=update)


def wrote_every_axis(record: Any, axes: int) -> bool:
    """Every configured axis wrote this cycle (a single-axis record has no ``axes``)."""
    if axes == 1 and not record.axes:
        return bool(record.write_status.startswith("ok"))
    if len(record.axes) != axes:
        raise RuntimeError(
            f"the loop recorded {len(record.axes)} axes of {axes}: it does not run every "
            "axis of compensation.axes"
        )
    return all(a.write_status.startswith("ok") for a in record.axes.values())


async def measure_block(
    name: str, machine: MachineSection, cycles: int, requests: list[int]
) -> list[float]:
    """CPU seconds of ``cycles`` cycles that wrote every axis, on a fresh loop; the
    requests each of them sent are appended to ``requests``."""
    # The loop's own clock moves one cycle (1 s) per cycle, so its slew budget and
    # hold timers see 1 s cycles; the cycles themselves run back to back.
    clock = ManualClock()
    loop = MachineLoop(
        machine, clock, build_buses(machine), build_cnc(machine, clock), load_bank(machine)
    )
    cpu: list[float] = []
    try:
        for _ in range(WARM_UP_CYCLES):
            clock.advance(machine.cycle_s)
            await loop.run_cycle()
        for _ in range(20 * cycles):  # bounded: a dead link must end the run, not hang it
            if len(cpu) >= cycles:
                break
            await asyncio.sleep(PACE_S)  # the simulator publishes new values in between
            clock.advance(machine.cycle_s)
            assert REQUESTS is not None
            sent = REQUESTS.sent
            start = time.process_time()
            record = await loop.run_cycle()
            spent = time.process_time() - start
            if wrote_every_axis(record, len(machine.axis_sections())):
                cpu.append(spent)
                requests.append(REQUESTS.sent - sent)
    finally:
        await loop.close()
    if len(cpu) < cycles:
        raise RuntimeError(f"{name}: only {len(cpu)} of {cycles} cycles wrote every axis")
    return cpu


def summary_us(samples: list[float]) -> dict[str, float]:
    values = np.asarray(samples) * 1e6
    return {
        "median_us": round(float(np.median(values)), 1),
        "mean_us": round(float(np.mean(values)), 1),
        "p90_us": round(float(np.percentile(values, 90)), 1),
        "cycles": int(values.size),
    }


async def main_async(args: argparse.Namespace) -> dict[str, Any]:
    global REQUESTS
    REQUESTS = RequestCounter()
    folder = Path(tempfile.mkdtemp(prefix="axes-cycle-cost-"))
    write_training_data(folder / "training.csv", seed=1)
    targets = axis_targets()
    # A single-axis machine's store holds one target; the three-axis store holds all.
    fit_models(folder / "training.csv", folder / "z", "benchmark", (targets["Z"],))
    fit_models(
        folder / "training.csv", folder / "xyz", "benchmark", [targets[a] for a in THREE_AXES]
    )
    ports = {"bus": free_port(), "opcua": free_port(), "modbus": free_port()}
    simulator = start_simulator(folder, ports)
    try:
        if hasattr(os, "sched_setaffinity") and (os.cpu_count() or 1) > 1:
            os.sched_setaffinity(0, {0})
        machines = {
            "one_axis": section(folder / "z", ports, args.cnc, ("Z",)),
            "three_axes": section(folder / "xyz", ports, args.cnc, THREE_AXES),
        }
        cpu: dict[str, list[float]] = {name: [] for name in machines}
        requests: dict[str, list[int]] = {name: [] for name in machines}
        blocks = max(1, args.cycles // args.block)
        for _ in range(blocks):
            for name, machine in machines.items():
                cpu[name] += await measure_block(name, machine, args.block, requests[name])
    except BaseException:
        if simulator.poll() is not None:
            print((folder / "simulator.log").read_text()[-3000:], file=sys.stderr)
        raise
    finally:
        simulator.terminate()
        simulator.wait(timeout=10)
    one, three = summary_us(cpu["one_axis"]), summary_us(cpu["three_axes"])
    for name, summary in (("one_axis", one), ("three_axes", three)):
        summary["requests_per_cycle"] = round(float(np.mean(requests[name])), 2)
    return {
        "cnc_protocol": args.cnc,
        "one_axis": one,
        "three_axes": three,
        "ratio_median": round(three["median_us"] / one["median_us"], 3),
        "ratio_mean": round(three["mean_us"] / one["mean_us"], 3),
        "target_ratio": 1.5,
        "cores_used_by_gateway": 1,
    }


def main() -> None:
    import logging

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    logging.getLogger("gateway.live.loop").setLevel(logging.CRITICAL)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=300, help="per configuration")
    parser.add_argument("--block", type=int, default=50, help="cycles per alternating block")
    parser.add_argument("--cnc", choices=["modbus", "opcua"], default="modbus")
    args = parser.parse_args()
    print(json.dumps(asyncio.run(main_async(args)), indent=2))


if __name__ == "__main__":
    main()
