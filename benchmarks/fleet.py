"""A fleet on one broker: several gateway processes as Sparkplug B edge nodes.

``--gateways`` processes (default 4) each run a whole :class:`gateway.wiring.Gateway`
over ``--machines`` simulated Modbus TCP machines (default 250, at a 1 s cycle; the
lean device servers of benchmarks/poll_vs_telegraf.py) and publish to one Mosquitto 2
on loopback (plain MQTT, QoS 1, no primary host). Measured, with Sparkplug off and
then on, over ``--window-s`` after ``--warmup-s``:

- ``cpu_ms_per_machine_cycle``: CPU of the gateway processes (utime + stime, all
  threads) divided by the cycles they ran; ``due_cycles_share``: cycles run /
  (machines × window);
- ``broker_msgs_per_s``: messages a subscriber to ``spBv1.0/#`` received, and the
  broker's own CPU share;
- ``births_after_restart_s``: the broker is killed (SIGKILL) and started again; the
  time from its start until the subscriber has seen every NBIRTH and every DBIRTH.

Prints one JSON document.

    .venv/bin/python benchmarks/fleet.py [--gateways 4] [--machines 250] [--window-s 30]
"""

from __future__ import annotations

import argparse
import asyncio
import faulthandler
import json
import multiprocessing
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.poll_vs_telegraf import Devices, fit_store, process_cpu_s, project_section
from tests.ports import free_tcp_port, wait_for_port

GROUP = "fleet"


def start_broker(folder: Path, port: int) -> subprocess.Popen[bytes]:
    user = "user root\n" if os.geteuid() == 0 else ""
    conf = folder / "mosquitto.conf"
    conf.write_text(
        f"{user}allow_anonymous true\npersistence false\nmax_queued_messages 1000000\n"
        f"max_inflight_messages 0\nlistener {port} 127.0.0.1\n"
    )
    process = subprocess.Popen(
        ["/usr/sbin/mosquitto", "-c", str(conf)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    wait_for_port(port, timeout_s=15)
    return process


def _gateway_main(index: int, ports: list[int], store: Path, folder: Path, broker_port: int,
                  sparkplug: bool, cycles: Any, started: Any,
                  stop_after_s: float) -> None:  # fmt: skip
    """One gateway process: its machines, Sparkplug on or off, counting cycles."""
    from gateway.config import GatewayConfig
    from gateway.wiring import Gateway

    machines = [
        project_section(store, port, index * 10_000 + i).model_dump(mode="json")
        for i, port in enumerate(ports)
    ]
    state = folder / f"gw{index}"
    document: dict[str, Any] = {
        "state_dir": str(state),
        "logging": {"local_store": str(state / "points.sqlite")},
        "machines": machines,
    }
    if sparkplug:
        document["sparkplug"] = {
            "brokers": [f"mqtt://127.0.0.1:{broker_port}"],
            "group_id": GROUP,
            "edge_node_id": f"edge{index}",
            "qos": 1,  # as measured in docs/fleet.md: every point acknowledged by the broker
            "startup_delay_max_s": 2.0,
            "reconnect_max_s": 2.0,
            "buffer_path": str(state / "spb.sqlite"),
        }
    config = GatewayConfig.model_validate(document)

    seen: set[str] = set()

    def count(record: Any) -> None:
        with cycles.get_lock():
            cycles.value += 1
        if record.machine not in seen:  # its first cycle: one more machine running
            seen.add(record.machine)
            with started.get_lock():
                started.value += 1

    faulthandler.dump_traceback_later(stop_after_s + 300, exit=True)  # a stop that hangs

    async def main() -> None:
        gateway = Gateway(config, sinks=[count])
        stop = asyncio.Event()
        asyncio.get_running_loop().call_later(stop_after_s, stop.set)
        await gateway.run(stop)

    asyncio.run(main())


class Counter:
    """A subscriber to the group: messages by kind, births seen, since a mark."""

    def __init__(self, port: int) -> None:
        self.lock = threading.Lock()
        self.total = 0
        self.births: set[str] = set()
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id="fleet-counter")
        self.client.on_connect = lambda c, *_: c.subscribe(f"spBv1.0/{GROUP}/#", qos=1)
        self.client.on_message = self._message
        self.client.reconnect_delay_set(0.05, 0.2)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def _message(self, _c: Any, _u: Any, message: paho.MQTTMessage) -> None:
        parts = message.topic.split("/")
        with self.lock:
            self.total += 1
            if parts[2] in ("NBIRTH", "DBIRTH"):
                self.births.add("/".join(parts[2:]))

    def read(self) -> tuple[int, int]:
        with self.lock:
            return self.total, len(self.births)

    def reset_births(self) -> None:
        with self.lock:
            self.births.clear()


def run_mode(args: argparse.Namespace, devices: Devices, store: Path, folder: Path,
             sparkplug: bool) -> dict[str, Any]:  # fmt: skip
    port = free_tcp_port()
    broker = start_broker(folder, port)
    counter = Counter(port)
    context = multiprocessing.get_context("spawn")
    cycles = context.Value("Q", 0)
    started = context.Value("Q", 0)  # machines that ran their first cycle
    per = args.machines
    length = args.warmup_s + args.window_s + (90 if sparkplug else 0) + 10
    processes = [
        context.Process(
            target=_gateway_main,
            args=(
                i,
                devices.ports[i * per : (i + 1) * per],
                store,
                folder / ("on" if sparkplug else "off"),
                port,
                sparkplug,
                cycles,
                started,
                length,
            ),
        )
        for i in range(args.gateways)
    ]
    launched = time.monotonic()
    for process in processes:
        process.start()
    all_started_s = None
    while time.monotonic() - launched < args.warmup_s:
        if all_started_s is None and started.value == args.gateways * per:
            all_started_s = round(time.monotonic() - launched, 1)
        time.sleep(0.1)
    cpu0 = sum(process_cpu_s(p.pid) for p in processes if p.pid)
    broker_cpu0, (msgs0, _), cycles0, t0 = (
        process_cpu_s(broker.pid),
        counter.read(),
        cycles.value,
        time.monotonic(),
    )
    time.sleep(args.window_s)
    elapsed = time.monotonic() - t0
    cpu = sum(process_cpu_s(p.pid) for p in processes if p.pid) - cpu0
    ran = cycles.value - cycles0
    msgs = counter.read()[0] - msgs0
    result: dict[str, Any] = {
        "sparkplug": sparkplug,
        "all_machines_cycling_after_s": all_started_s,  # None: not all within the warm-up
        "machines_cycling_at_window_end": started.value,
        "cycles": ran,
        "due_cycles_share": round(ran / (args.gateways * per * elapsed / 1.0), 3),
        "cpu_ms_per_machine_cycle": round(1000 * cpu / max(ran, 1), 3),
        "gateway_cores_used": round(cpu / elapsed, 3),
        "broker_msgs_per_s": round(msgs / elapsed, 1),
        "broker_core_share": round((process_cpu_s(broker.pid) - broker_cpu0) / elapsed, 3),
    }
    if sparkplug:
        expected = args.gateways * (per + 1)
        broker.kill()
        broker.wait()
        counter.reset_births()
        time.sleep(1.0)
        broker = start_broker(folder, port)
        start = time.monotonic()
        while counter.read()[1] < expected and time.monotonic() - start < 90:
            time.sleep(0.02)
        result["births_seen"] = counter.read()[1]
        result["births_expected"] = expected
        result["births_after_restart_s"] = round(time.monotonic() - start, 2)
    for process in processes:
        process.join(timeout=length + 30)
    counter.client.loop_stop()
    broker.kill()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gateways", type=int, default=4)
    parser.add_argument("--machines", type=int, default=250, help="machines per gateway")
    parser.add_argument("--warmup-s", type=float, default=20.0)
    parser.add_argument("--window-s", type=float, default=30.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="fleet-") as tmp:
        folder = Path(tmp)
        store = fit_store(folder)
        devices = Devices(args.gateways * args.machines)
        try:
            runs = [run_mode(args, devices, store, folder, on) for on in (False, True)]
        finally:
            devices.close()
    print(json.dumps({
        "gateways": args.gateways, "machines_per_gateway": args.machines, "cycle_s": 1.0,
        "window_s": args.window_s, "cpus": os.cpu_count(), "python": platform.python_version(),
        "runs": runs,
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
