"""How long one compensation cycle takes, against the protocol round trips it is made of,
and how many machines one gateway process keeps at a 1 s cycle on one core.

The simulated machine runs in its own process (pinned to the other core when
there are two), serving Modbus TCP transmitters and the CNC over OPC UA and
Modbus TCP. This process is pinned to one core and measures:

1. ``cycle``: ``MachineLoop.run_cycle`` — read both transmitter modules and the
   spindle speed, check quality, select, predict, write #500, read it back — on
   cycles that wrote (deadband 0; the simulator's sensor noise is raised to
   σ 0.2 °C so the value changes every cycle, and the rate-of-change check is
   relaxed for 30 ms cycles). Cycles are paced 30 ms apart, as the bare sequence
   is, so both meet the simulator in the same state.
2. ``bare``: the same protocol operations done one after another with plain
   pymodbus / asyncua calls and nothing else: read 16 registers of each module,
   read speed, commanded speed and run mode, write a Double, read it back.
3. ``ratio`` = median cycle / median bare sequence.
4. ``machines_at_1s``: the largest N (of the tried counts) for which N loops, each
   with its own connections and a 1 s cycle, all keep their rate (≥ 97 % of the
   due cycles, median start delay < 100 ms) for ``--scale-seconds``.

Prints one JSON document. Figures are measured in this one run.

    .venv/bin/python benchmarks/loop_latency.py [--cycles 300] [--cnc modbus|opcua]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from asyncua import Client, ua  # noqa: E402
from pymodbus.client import AsyncModbusTcpClient  # noqa: E402

from drivers.clock import WallClock  # noqa: E402
from gateway.demo.compensate import fit_models, machine_config, write_training_data  # noqa: E402
from gateway.live.loop import MachineLoop  # noqa: E402
from gateway.wiring import build_buses, build_cnc, load_bank  # noqa: E402

NAMESPACE = "urn:spindle-gateway:simulated-cnc"
PACE_S = 0.03  # between measured cycles: the simulator publishes every 10 ms meanwhile


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_for_port(port: int, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise TimeoutError(f"nothing listens on port {port}")


def start_simulator(
    folder: Path, ports: dict[str, int], speedup: float = 1
) -> subprocess.Popen[bytes]:
    """The simulated machine in its own process, on the other core when there are two."""
    config = {
        "simulator": {
            "program": "const6000",
            "speedup": speedup,
            "publish_period_s": 0.01,
            # Noisy sensors: the readings, and so the compensation, change every cycle,
            # so every measured cycle writes and reads back.
            "machine": {"sensor_noise_C": 0.2},
            "transmitters": {
                "tcp": {
                    "port": ports["bus"],
                    "devices": [
                        {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
                        {"device_id": 2, "channels": ["T9", "ambient"]},
                    ],
                }
            },
            "cnc": {"opcua": {"port": ports["opcua"]}, "modbus": {"port": ports["modbus"]}},
        }
    }
    path = folder / "simulator.yaml"
    path.write_text(yaml.safe_dump(config))
    command = [sys.executable, "-m", "gateway", "simulate", "--config", str(path)]
    if os.cpu_count() and os.cpu_count() > 1 and _has_taskset():
        command = ["taskset", "-c", "1", *command]
    log = (folder / "simulator.log").open("w")
    proc = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    for port in ports.values():
        wait_for_port(port)
    return proc


def _has_taskset() -> bool:
    return subprocess.run(["which", "taskset"], capture_output=True).returncode == 0


def machine(store: Path, ports: dict[str, int], cnc: str):
    link = (
        {"opcua": {"endpoint": f"opc.tcp://127.0.0.1:{ports['opcua']}/cnc", "timeout_s": 2.0}}
        if cnc == "opcua"
        else {"modbus": {"host": "127.0.0.1", "port": ports["modbus"], "timeout_s": 1.0}}
    )
    section = machine_config(
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
    )
    # Write every cycle: no deadband, a slew limit that never binds, and a rate-of-change
    # limit that 30 ms cycles of noisy sensors do not trip.
    comp = section.compensation.model_copy(update={"deadband_um": 0.0, "slew_um_per_min": 1e6})
    sensors = {name: {"max_rate_C_per_s": 1e6} for name in section.sensor_names}
    return type(section).model_validate(
        {**section.model_dump(), "compensation": comp.model_dump(), "sensors": sensors}
    )


def make_loop(section, clock) -> MachineLoop:
    return MachineLoop(
        section, clock, build_buses(section), build_cnc(section, clock), load_bank(section)
    )


def summary_ms(samples: list[float]) -> dict[str, float]:
    values = np.asarray(samples) * 1000.0
    return {
        "median_ms": round(float(np.median(values)), 3),
        "p99_ms": round(float(np.percentile(values, 99)), 3),
        "n": int(values.size),
    }


async def measure_cycle(section, cycles: int) -> list[float]:
    clock = WallClock()
    loop = make_loop(section, clock)
    times = []
    try:
        for _ in range(
            20
        ):  # warm up: quality needs 3 good checks, the first write starts the policy
            await loop.run_cycle()
        for _ in range(20 * cycles):  # bounded: a dead link must end the run, not hang it
            if len(times) >= cycles:
                break
            await asyncio.sleep(PACE_S)  # let the simulator publish new values in between
            start = time.perf_counter()
            record = await loop.run_cycle()
            elapsed = time.perf_counter() - start
            if record.write_status.startswith("ok"):
                times.append(elapsed)
    finally:
        await loop.close()
    if len(times) < cycles:
        raise RuntimeError(f"only {len(times)} of {cycles} cycles wrote; is the simulator up?")
    return times


async def measure_bare(ports: dict[str, int], cnc: str, cycles: int) -> list[float]:
    bus = AsyncModbusTcpClient("127.0.0.1", port=ports["bus"], timeout=1)
    await bus.connect()
    times = []
    if cnc == "modbus":
        cnc_client = AsyncModbusTcpClient("127.0.0.1", port=ports["modbus"], timeout=1)
        await cnc_client.connect()
        for i in range(cycles + 20):
            await asyncio.sleep(PACE_S)
            start = time.perf_counter()
            await bus.read_input_registers(0, count=16, device_id=1)
            await bus.read_input_registers(0, count=16, device_id=2)
            await cnc_client.read_holding_registers(0, count=5, device_id=1)
            registers = cnc_client.convert_to_registers(
                0.001 * (i % 7), cnc_client.DATATYPE.FLOAT32, word_order="big"
            )
            await cnc_client.write_registers(1000, registers, device_id=1)
            await cnc_client.read_holding_registers(1000, count=2, device_id=1)
            if i >= 20:
                times.append(time.perf_counter() - start)
        cnc_client.close()
    else:
        async with Client(f"opc.tcp://127.0.0.1:{ports['opcua']}/cnc") as client:
            idx = await client.get_namespace_index(NAMESPACE)
            nodes = [
                client.get_node(f"ns={idx};s={n}")
                for n in ("Spindle.ActualSpeed", "Spindle.CommandedSpeed", "Cnc.RunMode")
            ]
            macro = client.get_node(f"ns={idx};s=Macro.500")
            for i in range(cycles + 20):
                await asyncio.sleep(PACE_S)
                start = time.perf_counter()
                await bus.read_input_registers(0, count=16, device_id=1)
                await bus.read_input_registers(0, count=16, device_id=2)
                await client.read_values(nodes)
                await macro.write_value(
                    ua.DataValue(ua.Variant(0.001 * (i % 7), ua.VariantType.Double))
                )
                await macro.read_value()
                if i >= 20:
                    times.append(time.perf_counter() - start)
    bus.close()
    return times


async def keeps_up(section, machines: int, seconds: float) -> dict[str, float]:
    """Run ``machines`` loops at a 1 s cycle; how many due cycles ran, and how late."""
    clock = WallClock()
    loops = [make_loop(section, clock) for _ in range(machines)]
    starts: list[list[float]] = [[] for _ in loops]
    for i, loop in enumerate(loops):
        loop.sinks.append(lambda record, i=i: starts[i].append(record.time_s))
    stop = asyncio.Event()
    tasks = [asyncio.create_task(loop.run(stop)) for loop in loops]
    t0 = clock.now()
    await asyncio.sleep(seconds)
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    for loop in loops:
        await loop.close()
    due = machines * int(seconds)
    ran = sum(sum(1 for t in s if t - t0 < seconds) for s in starts)
    delays = [s[k] - (s[0] + k) for s in starts for k in range(len(s))]
    return {
        "machines": machines,
        "cycles_due": due,
        "cycles_run": ran,
        "share_run": round(ran / due, 4),
        "median_start_delay_ms": round(1000 * statistics.median(delays), 1) if delays else None,
    }


async def main_async(args: argparse.Namespace) -> dict[str, object]:
    folder = Path(tempfile.mkdtemp(prefix="loop-latency-"))
    write_training_data(folder / "training.csv", seed=1)
    fit_models(folder / "training.csv", folder / "models", "benchmark")
    ports = {"bus": free_port(), "opcua": free_port(), "modbus": free_port()}
    simulator = start_simulator(folder, ports)
    try:
        if hasattr(os, "sched_setaffinity") and (os.cpu_count() or 1) > 1:
            os.sched_setaffinity(0, {0})
        section = machine(folder / "models", ports, args.cnc)
        cycle = await measure_cycle(section, args.cycles)
        bare = await measure_bare(ports, args.cnc, args.cycles)
        scale = []
        best = 0
        for count in args.machines:
            outcome = await keeps_up(section, count, args.scale_seconds)
            scale.append(outcome)
            ok = outcome["share_run"] >= 0.97 and (outcome["median_start_delay_ms"] or 0) < 100
            if ok:
                best = count
            else:
                break
    except BaseException:
        if simulator.poll() is not None:
            print((folder / "simulator.log").read_text()[-3000:], file=sys.stderr)
        raise
    finally:
        simulator.terminate()
        simulator.wait(timeout=10)
    cycle_s, bare_s = summary_ms(cycle), summary_ms(bare)
    return {
        "cnc_protocol": args.cnc,
        "cycle": cycle_s,
        "bare_round_trips": bare_s,
        "ratio_median": round(cycle_s["median_ms"] / bare_s["median_ms"], 3),
        "ratio_p99": round(cycle_s["p99_ms"] / bare_s["p99_ms"], 3),
        "machines_at_1s": best,
        "scaling": scale,
        "cores_used_by_gateway": 1,
    }


def main() -> None:
    import logging

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    logging.getLogger("gateway.live.loop").setLevel(logging.CRITICAL)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=300)
    parser.add_argument("--cnc", choices=["modbus", "opcua"], default="modbus")
    parser.add_argument("--machines", type=int, nargs="+", default=[50, 100, 200, 300, 400])
    parser.add_argument("--scale-seconds", type=float, default=15.0)
    args = parser.parse_args()
    print(json.dumps(asyncio.run(main_async(args)), indent=2))


if __name__ == "__main__":
    main()
