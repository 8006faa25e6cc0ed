"""What the web console costs a whole gateway's cycles: 200 machines over Modbus TCP.

One :class:`gateway.wiring.Gateway` in this process, on uvloop as ``run`` starts it,
polls ``--machines`` (default 200) simulated machines at a 1 s cycle: the lean Modbus
TCP device servers of ``benchmarks/poll_vs_telegraf.py`` in other processes, two
transmitter modules and the CNC's macro per machine, each read, predicted, written
and read back every cycle. It logs to a local store and serves the web console.
A sink takes every cycle's start lateness (``MachineLoop.start_late_s``: how long
after its due time the cycle began, which includes the scheduler's 5 ms tick and
the loops released in the same burst before it).

Windows of ``--window-s`` alternate without a browser and with ``--browsers``
(default 20) overview pages open, ``--rounds`` times (default 3), beginning and
ending without; each page is a logged-in client in another process keeping the
overview's server-sent event stream (``benchmarks/console_cost.py``'s ``browsers``).
Reported per window: cycles, lateness median / p99 / max, the gateway process's CPU
per machine-cycle; and the p99 of every window with browsers over that of every
window without.

Prints one JSON document.

    .venv/bin/python benchmarks/console_gateway_cost.py [--machines 200] [--browsers 20]
        [--window-s 30] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.console_cost import USER, p, summary, with_browsers
from benchmarks.poll_vs_telegraf import Devices, fit_store, process_cpu_s, project_section
from tests.ports import free_tcp_port

PASSWORD_ENV = "CONSOLE_BENCH_PASSWORD"


def gateway_config(devices: Devices, store: Path, folder: Path, web_port: int) -> Any:
    from gateway.config import GatewayConfig

    machines = [
        project_section(store, port, i).model_dump(mode="json")
        for i, port in enumerate(devices.ports)
    ]
    os.environ[PASSWORD_ENV] = USER[1]
    return GatewayConfig.model_validate(
        {
            "state_dir": str(folder / "state"),
            "logging": {"local_store": str(folder / "points.sqlite")},
            "machines": machines,
            "web": {
                "port": web_port,
                "users": [{"username": USER[0], "password_env": PASSWORD_ENV}],
            },
        }
    )


class Windows:
    """The gateway's sink: each cycle's start lateness, into the window open now."""

    def __init__(self) -> None:
        self.loops: dict[str, Any] = {}
        self.current: list[float] = []
        self.seen: set[str] = set()

    def __call__(self, record: Any) -> None:
        self.current.append(self.loops[record.machine].start_late_s)
        self.seen.add(record.machine)

    async def window(self, seconds: float) -> tuple[list[float], float]:
        """(lateness of every cycle started within ``seconds``, CPU-s of this process)."""
        cpu0 = process_cpu_s(os.getpid())
        self.current = samples = []
        await asyncio.sleep(seconds)
        self.current = []
        return samples, process_cpu_s(os.getpid()) - cpu0


async def measure(gateway: Any, windows: Windows, args: argparse.Namespace) -> dict[str, Any]:
    stop = asyncio.Event()
    running = asyncio.create_task(gateway.run(stop))
    started = time.monotonic()
    while len(windows.seen) < args.machines and time.monotonic() - started < 120:
        await asyncio.sleep(0.5)
    all_cycling_s = round(time.monotonic() - started, 1)
    await asyncio.sleep(5.0)  # warm-up
    url = f"http://127.0.0.1:{gateway.config.web.port}"
    alone, watched = [await windows.window(args.window_s)], []
    for _ in range(args.rounds):
        watched.append(await with_browsers(url, args, lambda: windows.window(args.window_s)))
        alone.append(await windows.window(args.window_s))
    stop.set()
    await running
    return {"all_machines_cycling_after_s": all_cycling_s, **report(alone, watched, args)}


def _window(browsers_open: int, samples: list[float], cpu_s: float) -> dict[str, Any]:
    return {
        "browsers": browsers_open,
        **summary(samples),
        "cpu_ms_per_machine_cycle": round(1000 * cpu_s / max(len(samples), 1), 3),
    }


def report(alone: list, watched: list, args: argparse.Namespace) -> dict[str, Any]:
    rows = [_window(0, *alone[0])]
    for (w, w_cpu), (a, a_cpu) in zip(watched, alone[1:], strict=True):
        rows += [_window(args.browsers, w, w_cpu), _window(0, a, a_cpu)]
    without = [x for samples, _ in alone for x in samples]
    with_ = [x for samples, _ in watched for x in samples]
    return {
        "windows": rows,
        "p99_ms_without": round(p(without, 0.99), 2),
        f"p99_ms_with_{args.browsers}": round(p(with_, 0.99), 2),
        "p99_ratio": round(p(with_, 0.99) / p(without, 0.99), 3),
        "p99_ratio_per_round": [
            round(p(w, 0.99) / p(alone[k][0] + alone[k + 1][0], 0.99), 3)
            for k, (w, _) in enumerate(watched)
        ],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--machines", type=int, default=200)
    parser.add_argument("--browsers", type=int, default=20)
    parser.add_argument("--window-s", type=float, default=30.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    from gateway.process.event_loop import run
    from gateway.wiring import Gateway

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        devices = Devices(args.machines)
        store = fit_store(folder)
        config = gateway_config(devices, store, folder, free_tcp_port())

        async def main_async() -> dict[str, Any]:
            windows = Windows()
            gateway = Gateway(config, sinks=[windows])
            windows.loops = {loop.config.id: loop for loop in gateway.loops}
            return await measure(gateway, windows, args)

        result = run(main_async())
    result["machine"] = {
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "load_average": os.getloadavg(),
    }
    result["args"] = vars(args)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
