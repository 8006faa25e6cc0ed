"""The gateway's Modbus poll path against Telegraf's, side by side, on the same devices.

Telegraf v1.39.3 (``scripts/build-telegraf.sh``) and the gateway poll the same N
simulated Modbus TCP machines, one after the other and interleaved (Telegraf, the
gateway's poll, the gateway's full cycle; then again, ``--repeats`` times), each
for ``--window-s`` after a warm-up. Every machine is one TCP port with:

- two Pt100 input modules (device ids 1 and 2, input registers 0–15: eight
  0.1 °C values, eight statuses), the shipped transmitter map;
- the CNC on device id 1: holding registers 0–4 (actual and commanded speed as
  float32, run mode) and macro #500 at 1000–1001 (float32, writable).

Both sides read the same four requests per machine and cycle (both modules, the
speed block, the macro), at a 1 s interval:

- ``telegraf``: ``inputs.modbus`` (request style, one plugin instance per
  machine, one connection each) into ``outputs.discard``; config generated per run.
- ``project_poll``: the gateway's drivers (``TransmitterBus.read_all``,
  ``ModbusCnc.read_speed`` and ``read_macro``) on the gateway's cycle scheduler.
- ``project_cycle``: the whole ``MachineLoop`` (quality, regime, model,
  write-back with read-back) per machine, as ``run`` starts them.

Both gateway sides run with the objects built at start frozen out of the
garbage collector's passes, as ``Gateway.run`` runs (:mod:`gateway.process.gc_tuning`).

The poller under test is pinned to core 0; the devices are served by lean
server processes (an asyncio protocol answering from a register image, a few
hundred ports per process) pinned to core 1, and they count every request they
answer. Pollers and servers run at nice −10 (as root), so other work on the
machine does not starve either side. CPU is the poller process's own (utime +
stime from ``/proc/<pid>/stat``, all threads), over the window. Reported per run and as medians:

- ``cpu_s_per_1000_requests`` and ``cpu_ms_per_machine_cycle``;
- ``due_cycles_share`` (cycles run / machines × window) and the core shares of
  the poller and of the servers: a side at ≥ 90 % of its core, or running
  fewer than 97 % of its due cycles, is ``saturated``;
- ratios project / Telegraf, taken per repeat (the neighbours in time) and then
  the median, so load from other work on the machine hits both alike.

Prints one JSON document.

    .venv/bin/python benchmarks/poll_vs_telegraf.py [--machines 50 200 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing
import os
import platform
import select
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from drivers.cnc import CncError  # noqa: E402
from gateway.live.loop import read_together  # noqa: E402

TELEGRAF = ROOT / ".cache" / "bin" / "telegraf"
POLLER_CORE = 0
SERVER_CORE = 1
PORTS_PER_SERVER = 250
CYCLE_S = 1.0
MACRO = 500
MACRO_REGISTER = 1000
REQUESTS_PER_MACHINE_CYCLE = 4  # both modules, the speed block, the macro
SATURATED_CORE_SHARE = 0.9
KEPT_UP_SHARE = 0.97
CLOCK_TICKS_S = os.sysconf("SC_CLK_TCK")
SIDES = ("telegraf", "project_poll", "project_cycle")
#: Scheduling priority of the pollers and servers (nice value): above the machine's other
#: work, so a busy neighbour does not starve either side; alike for both sides.
PRIORITY = -10


def raise_priority() -> int:
    """Give this process the benchmark's priority; the nice value it runs at."""
    with contextlib.suppress(PermissionError):  # not root: both sides at normal priority
        os.setpriority(os.PRIO_PROCESS, 0, PRIORITY)
    return os.getpriority(os.PRIO_PROCESS, 0)


# --- the simulated machines: lean Modbus TCP responders -------------------------------------


def _module_registers(values_C: list[float], bump: int) -> bytearray:
    """One Pt100 module's 16 input registers (values in 0.1 °C, then statuses 0)."""
    counts = [round(v * 10) + bump for v in values_C] + [0] * (8 - len(values_C))
    return bytearray(struct.pack(">8h8H", *counts, *([0] * 8)))


def _cnc_holding() -> bytearray:
    """Holding registers 0–1001 of the CNC: speed, commanded speed, run mode, macro #500."""
    table = bytearray(2 * (MACRO_REGISTER + 2))
    table[0:10] = struct.pack(">ffH", 6000.0, 6000.0, 1)
    table[2 * MACRO_REGISTER : 2 * MACRO_REGISTER + 4] = struct.pack(">f", 0.0)
    return table


#: Input registers per device id, in two images that differ by one count, served in
#: turn: readings that move by 0.1 °C are neither stuck nor too fast for the quality check.
INPUT_IMAGES = {
    1: (
        _module_registers([25.0, 25.5, 26.0, 26.5, 27.0, 27.5, 28.0, 28.5], 0),
        _module_registers([25.0, 25.5, 26.0, 26.5, 27.0, 27.5, 28.0, 28.5], 1),
    ),
    2: (_module_registers([22.0, 20.0], 0), _module_registers([22.0, 20.0], 1)),
}


class _Machine(asyncio.Protocol):
    """One machine's port: answers FC3, FC4 and FC16 from its register image."""

    def __init__(self, counter: Any) -> None:
        self._counter = counter
        self._holding = _cnc_holding()
        self._reads = 0
        self._buffer = b""
        self._transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport

    def data_received(self, data: bytes) -> None:
        buffer = self._buffer + data if self._buffer else data
        replies = []
        while len(buffer) >= 8:
            end = 6 + int.from_bytes(buffer[4:6], "big")
            if len(buffer) < end:
                break
            replies.append(self._answer(buffer[:end]))
            buffer = buffer[end:]
        self._buffer = buffer
        if replies and self._transport is not None:
            self._counter.value += len(replies)
            self._transport.write(b"".join(replies))

    def _answer(self, frame: bytes) -> bytes:
        unit, function = frame[6], frame[7]
        address, count = struct.unpack_from(">HH", frame, 8)
        pdu: bytes
        if function == 4 and unit in INPUT_IMAGES:
            self._reads += 1
            image = INPUT_IMAGES[unit][self._reads & 1]
            pdu = bytes((4, 2 * count)) + image[2 * address : 2 * (address + count)]
        elif function == 3 and unit == 1 and 2 * (address + count) <= len(self._holding):
            pdu = bytes((3, 2 * count)) + self._holding[2 * address : 2 * (address + count)]
        elif function == 16 and unit == 1 and 2 * (address + count) <= len(self._holding):
            self._holding[2 * address : 2 * (address + count)] = frame[13 : 13 + 2 * count]
            pdu = frame[7:12]
        else:
            pdu = bytes((function | 0x80, 2))  # illegal data address
        return frame[0:2] + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big") + bytes((unit,)) + pdu


def _serve(count: int, counter: Any, ports_out: Connection) -> None:
    """Server process: ``count`` machine ports; sends their numbers, serves until killed."""
    if hasattr(os, "sched_setaffinity") and (os.cpu_count() or 1) > 1:
        os.sched_setaffinity(0, {SERVER_CORE})
    raise_priority()

    async def main() -> None:
        loop = asyncio.get_running_loop()
        servers = [
            await loop.create_server(lambda: _Machine(counter), "127.0.0.1", 0, backlog=64)
            for _ in range(count)
        ]
        ports_out.send([s.sockets[0].getsockname()[1] for s in servers])
        await asyncio.Event().wait()

    asyncio.run(main())


class Devices:
    """The N simulated machines, in server processes of at most ``PORTS_PER_SERVER`` ports."""

    def __init__(self, machines: int) -> None:
        context = multiprocessing.get_context("fork")
        self.counters = []
        self.processes = []
        self.ports: list[int] = []
        for start in range(0, machines, PORTS_PER_SERVER):
            count = min(PORTS_PER_SERVER, machines - start)
            counter = context.RawValue("Q", 0)
            receive, send = context.Pipe(duplex=False)
            process = context.Process(target=_serve, args=(count, counter, send), daemon=True)
            process.start()
            self.ports += receive.recv()
            self.counters.append(counter)
            self.processes.append(process)

    def requests(self) -> int:
        return sum(int(c.value) for c in self.counters)

    def cpu_s(self) -> float:
        return sum(process_cpu_s(p.pid) for p in self.processes if p.pid is not None)

    def close(self) -> None:
        for process in self.processes:
            process.terminate()
        for process in self.processes:
            process.join(timeout=5)


def process_cpu_s(pid: int) -> float:
    """utime + stime of a whole process (every thread), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS_S


# --- Telegraf -------------------------------------------------------------------------------


def telegraf_config(ports: list[int]) -> str:
    """inputs.modbus per machine with the same four requests, 1 s interval, outputs.discard."""
    value_fields = ", ".join(
        f'{{ address={i}, name="T{i + 1}", type="INT16", scale=0.1 }}' for i in range(8)
    )
    status_fields = ", ".join(
        f'{{ address={8 + i}, name="S{i + 1}", type="UINT16" }}' for i in range(8)
    )
    parts = [
        "[agent]\n"
        '  interval = "1s"\n  round_interval = true\n  collection_jitter = "0s"\n'
        '  flush_interval = "1s"\n  flush_jitter = "0s"\n  metric_batch_size = 5000\n'
        "  metric_buffer_limit = 100000\n  omit_hostname = true\n  quiet = true\n"
        "[[outputs.discard]]\n"
    ]
    for index, port in enumerate(ports):
        parts.append(
            f"[[inputs.modbus]]\n"
            f'  name = "m{index}"\n  controller = "tcp://127.0.0.1:{port}"\n'
            f'  timeout = "1s"\n  configuration_type = "request"\n'
        )
        for device in (1, 2):
            parts.append(
                f"  [[inputs.modbus.request]]\n    slave_id = {device}\n"
                f'    byte_order = "ABCD"\n    register = "input"\n'
                f"    fields = [ {value_fields}, {status_fields} ]\n"
            )
        parts.append(
            "  [[inputs.modbus.request]]\n    slave_id = 1\n"
            '    byte_order = "ABCD"\n    register = "holding"\n'
            '    fields = [ { address=0, name="speed_rpm", type="FLOAT32" },'
            ' { address=2, name="commanded_rpm", type="FLOAT32" },'
            ' { address=4, name="run_mode", type="UINT16" } ]\n'
        )
        parts.append(
            "  [[inputs.modbus.request]]\n    slave_id = 1\n"
            '    byte_order = "ABCD"\n    register = "holding"\n'
            f'    fields = [ {{ address={MACRO_REGISTER}, name="macro_{MACRO}",'
            ' type="FLOAT32" } ]\n'
        )
    return "".join(parts)


def telegraf_version() -> str:
    out = subprocess.run([str(TELEGRAF), "--version"], capture_output=True, text=True)
    return out.stdout.strip()


# --- the gateway side: runs in its own process ------------------------------------------------


def project_section(store: Path, port: int, index: int):
    from gateway.demo.compensate import machine_config

    section = machine_config(
        store,
        transmitters=[
            {
                "name": "bus1",
                "tcp": {"host": "127.0.0.1", "port": port},
                "timeout_s": 0.5,
                "devices": [
                    {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
                    {"device_id": 2, "channels": ["T9", None]},
                ],
            }
        ],
        cnc={"modbus": {"host": "127.0.0.1", "port": port, "timeout_s": 1.0}},
        cycle_s=CYCLE_S,
    )
    return type(section).model_validate({**section.model_dump(), "id": f"m{index}"})


class Stats:
    """Start time, start delay and outcome of every cycle; the window is cut at the end."""

    def __init__(self) -> None:
        self.cycles: list[tuple[float, float, bool]] = []  # (start, late by, failed)
        self.marks: list[float] = []

    def window(self) -> dict[str, Any]:
        """The cycles that started between the first and the last mark."""
        start, end = self.marks[0], self.marks[-1]
        inside = [c for c in self.cycles if start <= c[0] < end]
        delays = sorted(c[1] for c in inside) or [0.0]
        return {
            "cycles": len(inside),
            "failed": sum(1 for c in inside if c[2]),
            "start_delay_p50_ms": round(1000 * delays[len(delays) // 2], 2),
            "start_delay_p99_ms": round(1000 * delays[int(0.99 * (len(delays) - 1))], 2),
        }


async def _poll_only(section, clock, stop: asyncio.Event, stats: Stats, scheduler) -> None:
    """One machine's poll on the gateway's scheduler: transmitters and speed together, then
    the macro (the reads of a full cycle, without the rest of it)."""
    from gateway.live.scheduler import after_cycle
    from gateway.wiring import build_buses, build_cnc

    cycle_s = section.cycle_s
    buses, cnc = build_buses(section), build_cnc(section, clock)
    # On the scheduler's grid, as MachineLoop.run: an overrun polls again at once, then
    # the next grid time.
    due = grid_due = scheduler.next_due_s(scheduler.phase_s(cycle_s), cycle_s)
    try:
        while not stop.is_set():
            await scheduler.wait_until(due, stop)
            if stop.is_set():
                break
            now = clock.now()
            await poll_once(buses, cnc, now, now - due, stats)
            due, grid_due = after_cycle(grid_due, cycle_s, clock.now())
    finally:
        for bus in buses:
            await bus.close()
        await cnc.close()


async def poll_once(buses, cnc, now: float, late_s: float, stats: Stats) -> None:
    outcomes, speed = await read_together([bus.read_all(now) for bus in buses], cnc.read_speed())
    failed = any(isinstance(o, BaseException) for o in [*outcomes, speed]) or any(
        r.error for o in outcomes if isinstance(o, dict) for r in o.values()
    )
    try:
        await cnc.read_macro(MACRO)
    except CncError:
        failed = True
    stats.cycles.append((now, late_s, failed))


async def _poller_main(args: argparse.Namespace) -> None:
    import logging

    from drivers.clock import WallClock
    from gateway.live.loop import MachineLoop
    from gateway.live.scheduler import CycleScheduler
    from gateway.process.gc_tuning import frozen_startup_heap
    from gateway.wiring import build_buses, build_cnc, load_bank

    logging.disable(logging.CRITICAL)  # a benchmark: no log formatting in the measurement
    ports = json.loads(Path(args.ports).read_text())
    store = Path(args.store)
    clock = WallClock()
    stop = asyncio.Event()
    stats = Stats()
    scheduler = CycleScheduler(clock)
    sections = [project_section(store, port, i) for i, port in enumerate(ports)]
    tasks = []
    loops: list[MachineLoop] = []
    if args.role == "project_poll":
        tasks = [
            asyncio.create_task(_poll_only(s, clock, stop, stats, scheduler)) for s in sections
        ]
    else:
        bank = load_bank(sections[0])  # the same store for every machine; the bank is read-only
        for section in sections:
            buses, cnc = build_buses(section), build_cnc(section, clock)
            loop = MachineLoop(section, clock, buses, cnc, bank)

            def sink(record, loop=loop) -> None:
                late_s = record.time_s - loop.due_s
                stats.cycles.append((record.time_s, late_s, bool(record.link_errors)))

            loop.sinks.append(sink)
            loops.append(loop)
        tasks = [
            asyncio.create_task(
                loop.run(stop, scheduler=scheduler, phase_s=scheduler.phase_s(CYCLE_S))
            )
            for loop in loops
        ]

    reader = asyncio.StreamReader()
    await asyncio.get_running_loop().connect_read_pipe(
        lambda: asyncio.StreamReaderProtocol(reader), sys.stdin
    )
    print(json.dumps({"ready": len(sections)}), flush=True)
    with frozen_startup_heap():  # as Gateway.run does, for both gateway sides
        while line := (await reader.readline()).decode().strip():
            if line == "mark":
                stats.marks.append(clock.now())
                print(json.dumps({"marked": len(stats.marks)}), flush=True)
            elif line == "stop":
                stop.set()
                break
        await asyncio.gather(*tasks, return_exceptions=True)
    for loop in loops:
        await loop.close()
    print(json.dumps(stats.window()), flush=True)


# --- one measured run ------------------------------------------------------------------------


class Poller:
    """The process under test, pinned to the poller core."""

    def __init__(
        self, side: str, ports: list[int], folder: Path, store: Path, event_loop: str
    ) -> None:
        self.side = side
        pin = ["taskset", "-c", str(POLLER_CORE)]
        if side == "telegraf":
            config = folder / "telegraf.conf"
            config.write_text(telegraf_config(ports))
            command = [*pin, str(TELEGRAF), "--config", str(config)]
            self.log = (folder / "telegraf.log").open("w")
            self.proc = subprocess.Popen(
                command, stdout=self.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
            )
        else:
            ports_file = folder / "ports.json"
            ports_file.write_text(json.dumps(ports))
            command = [
                *pin,
                sys.executable,
                str(Path(__file__).resolve()),
                "--poller",
                side,
                "--ports",
                str(ports_file),
                "--store",
                str(store),
                "--event-loop",
                event_loop,
            ]
            self.log = (folder / f"{side}.log").open("w")
            self.proc = subprocess.Popen(
                command,
                cwd=ROOT,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=self.log,
                text=True,
            )
            self._answer(timeout_s=300)  # {"ready": N}

    def _answer(self, timeout_s: float = 30) -> dict[str, Any]:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            raise RuntimeError(f"{self.side} did not answer (exit {self.proc.poll()})")
        return json.loads(line)

    def mark(self) -> dict[str, Any]:
        cpu = process_cpu_s(self.proc.pid)
        if self.side == "telegraf":
            return {"cpu_s": cpu}
        assert self.proc.stdin is not None
        self.proc.stdin.write("mark\n")
        self.proc.stdin.flush()
        return {"cpu_s": cpu, **self._answer()}

    def stop(self) -> dict[str, Any]:
        if self.side == "telegraf":
            self.proc.terminate()
            self.proc.wait(timeout=30)
            return {}
        assert self.proc.stdin is not None
        self.proc.stdin.write("stop\n")
        self.proc.stdin.flush()
        final = self._answer(timeout_s=60)
        self.proc.wait(timeout=30)
        return final


def measure(side: str, devices: Devices, folder: Path, store: Path, args) -> dict[str, Any]:
    machines = len(devices.ports)
    poller = Poller(side, devices.ports, folder, store, args.event_loop)
    try:
        time.sleep(args.warmup_s)
        if poller.proc.poll() is not None:
            raise RuntimeError(f"{side} exited early; see {folder}")
        first, requests0, servers0, t0 = (
            poller.mark(),
            devices.requests(),
            devices.cpu_s(),
            time.monotonic(),
        )
        time.sleep(args.window_s)
        last, requests1, servers1, t1 = (
            poller.mark(),
            devices.requests(),
            devices.cpu_s(),
            time.monotonic(),
        )
    finally:
        final = poller.stop()
    window_s = t1 - t0
    cpu_s = last["cpu_s"] - first["cpu_s"]
    requests = requests1 - requests0
    if side == "telegraf":
        cycles = requests / REQUESTS_PER_MACHINE_CYCLE
        failed = None
    else:
        cycles = final.pop("cycles")
        failed = final.pop("failed")
    due = machines * window_s / CYCLE_S
    poller_share = cpu_s / window_s
    server_share = (servers1 - servers0) / window_s
    kept_up = cycles / due
    return {
        "machines": machines,
        "side": side,
        "window_s": round(window_s, 2),
        "cpu_s": round(cpu_s, 3),
        "requests": requests,
        "machine_cycles": round(cycles),
        "failed_cycles": failed,
        "requests_per_machine_cycle": round(requests / cycles, 3) if cycles else None,
        "cpu_s_per_1000_requests": round(1000 * cpu_s / requests, 4) if requests else None,
        "cpu_ms_per_machine_cycle": round(1000 * cpu_s / cycles, 4) if cycles else None,
        "due_cycles_share": round(kept_up, 4),
        "poller_core_share": round(poller_share, 3),
        "server_core_share": round(server_share, 3),
        "saturated": saturated(poller_share, server_share, kept_up),
        **final,
    }


def saturated(poller_share: float, server_share: float, kept_up: float) -> str | None:
    """Which side ran out of CPU: the poller's core, the servers' core, or None.

    Cycles missed while both cores had headroom are ``"neither"``: the machine's
    other load held the poller up (the run's CPU figures stay valid).
    """
    if poller_share >= SATURATED_CORE_SHARE:
        return "poller"
    if server_share >= SATURATED_CORE_SHARE:
        return "servers"
    return "neither" if kept_up < KEPT_UP_SHARE else None


def _median(values: list[float]) -> float | None:
    values = [v for v in values if v is not None]
    return round(statistics.median(values), 4) if values else None


def summarise(runs: list[dict[str, Any]], machines: list[int]) -> dict[str, Any]:
    summary: dict[str, Any] = {}
    for count in machines:
        mine = [r for r in runs if r["machines"] == count]
        by_side = {
            side: {
                "cpu_s_per_1000_requests": _median(
                    [r["cpu_s_per_1000_requests"] for r in mine if r["side"] == side]
                ),
                "cpu_ms_per_machine_cycle": _median(
                    [r["cpu_ms_per_machine_cycle"] for r in mine if r["side"] == side]
                ),
                "due_cycles_share": _median(
                    [r["due_cycles_share"] for r in mine if r["side"] == side]
                ),
                "poller_core_share": _median(
                    [r["poller_core_share"] for r in mine if r["side"] == side]
                ),
                "runs_short_of_due_cycles": sum(
                    1 for r in mine if r["side"] == side and r["due_cycles_share"] < KEPT_UP_SHARE
                ),
                "saturated": sorted(
                    {r["saturated"] for r in mine if r["side"] == side and r["saturated"]}
                ),
            }
            for side in SIDES
        }
        ratios: dict[str, list[float]] = {"poll_per_request": [], "cycle_per_machine_cycle": []}
        ratios["poll_per_machine_cycle"] = []
        for repeat in sorted({r["repeat"] for r in mine}):
            row = {r["side"]: r for r in mine if r["repeat"] == repeat}
            tel = row.get("telegraf")
            if not tel or not tel["cpu_s_per_1000_requests"]:
                continue
            if "project_poll" in row and row["project_poll"]["cpu_s_per_1000_requests"]:
                ratios["poll_per_request"].append(
                    row["project_poll"]["cpu_s_per_1000_requests"] / tel["cpu_s_per_1000_requests"]
                )
                ratios["poll_per_machine_cycle"].append(
                    row["project_poll"]["cpu_ms_per_machine_cycle"]
                    / tel["cpu_ms_per_machine_cycle"]
                )
            if "project_cycle" in row and row["project_cycle"]["cpu_ms_per_machine_cycle"]:
                ratios["cycle_per_machine_cycle"].append(
                    row["project_cycle"]["cpu_ms_per_machine_cycle"]
                    / tel["cpu_ms_per_machine_cycle"]
                )
        summary[str(count)] = {
            **by_side,
            "ratio_project_to_telegraf": {
                name: {
                    "median": _median(values),
                    "range": [round(min(values), 3), round(max(values), 3)] if values else None,
                }
                for name, values in ratios.items()
            },
        }
    return summary


def ceiling(runs: list[dict[str, Any]], summary: dict[str, Any]) -> dict[str, Any]:
    """Machines one process keeps at a 1 s full cycle on one core: measured and CPU-bound."""
    kept = [
        r["machines"]
        for r in runs
        if r["side"] == "project_cycle" and r["due_cycles_share"] >= KEPT_UP_SHARE
    ]
    largest = max((m for m in set(kept) if kept.count(m) >= 2), default=0)
    costs = {n: s["project_cycle"]["cpu_ms_per_machine_cycle"] for n, s in summary.items()}
    cost_at_largest = costs.get(str(max(int(n) for n in costs)))
    return {
        "full_cycle_machines_kept_at_1s": largest,
        "kept_means": f"≥ {KEPT_UP_SHARE:.0%} of due cycles in at least 2 repeats",
        "full_cycle_cpu_bound_estimate": (
            int(1000 * CYCLE_S / cost_at_largest) if cost_at_largest else None
        ),
        "estimate_means": "one core / CPU per machine-cycle at the largest N",
    }


def fit_store(folder: Path) -> Path:
    from gateway.demo.compensate import fit_models, write_training_data

    write_training_data(folder / "training.csv", seed=1)
    fit_models(folder / "training.csv", folder / "models", "benchmark")
    return folder / "models"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, nargs="+", default=[50, 200, 1000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--window-s", type=float, default=20.0)
    parser.add_argument("--warmup-s", type=float, default=6.0)
    parser.add_argument("--sides", nargs="+", choices=SIDES, default=list(SIDES))
    parser.add_argument(
        "--event-loop",
        choices=("uvloop", "asyncio"),
        default="uvloop",
        help="the gateway sides' event loop (the config's event_loop; default as run)",
    )
    parser.add_argument("--poller", choices=SIDES[1:], help=argparse.SUPPRESS)
    parser.add_argument("--ports", help=argparse.SUPPRESS)
    parser.add_argument("--store", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.poller:
        raise_priority()
        args.role = args.poller
        from gateway.process import event_loop

        event_loop.run(_poller_main(args), args.event_loop)
        return
    if "telegraf" in args.sides and not TELEGRAF.exists():
        print(f"{TELEGRAF} is missing: run scripts/build-telegraf.sh first", file=sys.stderr)
        raise SystemExit(2)
    if hasattr(os, "sched_setaffinity") and (os.cpu_count() or 1) > 1:
        os.sched_setaffinity(0, {SERVER_CORE})  # the conductor stays off the poller's core
    nice = raise_priority()
    folder = Path(tempfile.mkdtemp(prefix="poll-vs-telegraf-"))
    runs = []
    try:
        store = fit_store(folder)
        for count in args.machines:
            devices = Devices(count)
            try:
                for repeat in range(args.repeats):
                    for side in args.sides:
                        run = measure(side, devices, folder, store, args)
                        runs.append({"repeat": repeat, **run})
                        print(json.dumps(runs[-1]), file=sys.stderr, flush=True)
            finally:
                devices.close()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    summary = summarise(runs, args.machines)
    import pymodbus

    print(
        json.dumps(
            {
                "telegraf": telegraf_version() if "telegraf" in args.sides else None,
                "python": platform.python_version(),
                "pymodbus": pymodbus.__version__,
                "event_loop": args.event_loop,
                "cycle_s": CYCLE_S,
                "requests_per_machine_cycle": REQUESTS_PER_MACHINE_CYCLE,
                "cores": {"poller": POLLER_CORE, "servers": SERVER_CORE},
                "nice": nice,
                "window_s": args.window_s,
                "repeats": args.repeats,
                "summary": summary,
                "ceiling": ceiling(runs, summary) if "project_cycle" in args.sides else None,
                "runs": runs,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
