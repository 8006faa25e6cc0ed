"""A bench of processes for tests: ``python -m gateway simulate`` serving one machine and
``python -m gateway run`` compensating it, from one configuration file.

:func:`bench_config` is that file's content (the simulator's Modbus TCP transmitters
and Modbus CNC, one machine reaching them); a test changes what it needs in the
returned dict. :func:`read_macro_mm` reads a CNC macro over Modbus as a SCADA would.
"""

from __future__ import annotations

import contextlib
import itertools
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml
from pymodbus.client import ModbusTcpClient

from tests import gateway_rig as rig
from tests.ports import wait_for_port

ROOT = Path(__file__).resolve().parent.parent


def gateway_process(*args: str | Path) -> subprocess.Popen[str]:
    """``python -m gateway ARGS`` as its own process, its output captured."""
    return subprocess.Popen(
        [sys.executable, "-m", "gateway", *(str(a) for a in args)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@contextlib.contextmanager
def simulator_serving(
    config: Path, cnc: int, stop: signal.Signals = signal.SIGINT
) -> Iterator[subprocess.Popen[str]]:
    """``simulate --config CONFIG`` for the block, its CNC port ``cnc`` answering before
    the block starts; stopped by ``stop`` at the end."""
    simulator = gateway_process("simulate", "--config", config)
    try:
        wait_for_port(cnc)
        yield simulator
    finally:
        simulator.send_signal(stop)
        simulator.communicate(timeout=30)


@contextlib.contextmanager
def bench_running(config: Path, cnc: int, log_path: Path) -> Iterator[subprocess.Popen[str]]:
    """``simulate`` and ``run`` on CONFIG, their stdout let go and the gateway's log
    (stderr) in ``log_path``; the block starts once the loop has read the CNC's macro,
    and both processes are stopped at its end (SIGTERM, then the simulator by SIGINT)."""
    quiet: dict[str, Any] = {"cwd": ROOT, "stdout": subprocess.DEVNULL, "text": True}
    command = [sys.executable, "-m", "gateway"]
    simulator = subprocess.Popen([*command, "simulate", "--config", str(config)], **quiet)
    running = None
    try:
        wait_for_port(cnc)
        with open(log_path, "w") as log:
            running = subprocess.Popen(
                [*command, "run", "--config", str(config)], stderr=log, **quiet
            )
        assert wait_until(lambda: "CNC macro #500 holds" in log_path.read_text(), 90)
        yield running
    finally:
        if running is not None and running.poll() is None:
            running.send_signal(signal.SIGTERM)
            running.wait(timeout=30)
        simulator.send_signal(signal.SIGINT)
        simulator.wait(timeout=30)


def kill_if_running(*processes: subprocess.Popen[str] | None) -> None:
    """Kill what a failed test left running (and collect its output)."""
    for process in processes:
        if process is not None and process.poll() is None:
            process.kill()
            process.communicate()


def wait_until(condition: Callable[[], bool], timeout_s: float = 60.0) -> bool:
    """Poll ``condition`` every 0.1 s until it holds or ``timeout_s`` passes; its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not condition():
        time.sleep(0.1)
    return condition()


def wait_for_file(path: Path, process: subprocess.Popen[str], timeout_s: float) -> None:
    """Until ``path`` exists; fails at once when ``process`` ends first (with its output)."""
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, f"no {path.name} after {timeout_s:g} s"
        time.sleep(0.05)


def read_macro_mm(port: int, number: int = 500) -> float:
    """CNC macro ``#number`` (mm) from the simulator's Modbus CNC on ``port``."""
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    assert client.connect()
    try:
        rr = client.read_holding_registers(1000 + 2 * (number - 500), count=2, device_id=1)
        assert not rr.isError(), rr
        return float(
            client.convert_from_registers(rr.registers, client.DATATYPE.FLOAT32, word_order="big")
        )
    finally:
        client.close()


def rises(values: list[float]) -> int:
    """How often a value is above the one before it."""
    return sum(b > a for a, b in itertools.pairwise(values))


def bench_config(
    store: Path, bus: int, cnc: int, *, speedup: float, cycle_s: float = 0.2
) -> dict[str, Any]:
    """One simulated machine (programme const8000 at ×``speedup``; transmitters on Modbus
    TCP port ``bus``, CNC on Modbus port ``cnc``) and the gateway compensating it with the
    models of ``store`` (:func:`tests.gateway_rig.fit_store`)."""
    return {
        "simulator": {
            "program": "const8000",
            "speedup": speedup,
            "transmitters": {"tcp": {"port": bus, "devices": rig.DEVICES}},
            "cnc": {"modbus": {"port": cnc}},
        },
        "machines": [
            {
                "id": "bench-1",
                "cycle_s": cycle_s,
                "transmitters": [rig.tcp_bus("127.0.0.1", bus)],
                "sensors": {name: {"max_rate_C_per_s": 50.0} for name in rig.SENSORS},
                # The machine runs ×speedup faster than the wall clock: so does its growth.
                "plausibility": {"max_prediction_rate_um_per_s": speedup * 0.1},
                "cnc": {"modbus": {"host": "127.0.0.1", "port": cnc}},
                "compensation": {"slew_um_per_min": 2000.0},
                "models": rig.demo_models(store),
            }
        ],
    }


def write_config(config: dict[str, Any], path: Path) -> Path:
    """``config`` as the YAML file ``path``."""
    path.write_text(yaml.safe_dump(config), encoding="utf-8")
    return path
