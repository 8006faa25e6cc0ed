"""What the web console costs the compensation cycles, and how fast a machine page loads.

1. ``lateness`` (before, with browsers, after; the ratio against both windows
   without browsers together): ``--machines`` (default 200) machine tasks in one uvloop event loop,
   each on a 1 s cycle at its own phase, hand a nine-sensor ``CycleRecord`` to the
   console's sink every cycle, as the gateway's loops do; the console's aiohttp server
   runs in the same loop. Lateness is how long after its due time a cycle starts.
   Measured over windows of ``--window-s``, alternately without a browser and with
   ``--browsers`` (default 20) overview pages open, ``--rounds`` times (default 3),
   beginning and ending without: each page a logged-in client in another process
   that keeps the overview's server-sent event stream, as a browser tab does. The
   ratio is the p99 of every window with browsers over that of every window without.
   The machines are synthetic (no protocol I/O): what is measured is the console's
   share of the event loop, not the loops' own polling.
2. ``machine_page``: a local store holding 24 h of one machine at 1 Hz (86 400 cycles,
   nine sensors, a probe every 2 min) is served; the time to load the page and its
   plot, first (cold: read and drawn) and again (cached), over HTTP; and cold in
   headless Chromium (navigation start until the plot image is complete) when it is
   installed; and the read and the drawing timed alone in this process (wall and CPU
   seconds). ``--only-page`` measures this part only. The store is written in the
   earlier JSON layout and converted on opening (``converted_s``); ``--days`` fills
   more days before the last 24 h (``--hours`` sets the page's window: 720 is the
   30-day page); ``--store`` serves a store already filled (its machine ``m000``).
   Chromium loads the page in a new browser, then three more times, each with the
   console's drawn results forgotten (read and drawn afresh, the browser's own cache
   warm).

Prints one JSON document.

    .venv/bin/python benchmarks/console_cost.py [--machines 200] [--browsers 20]
        [--window-s 30] [--rounds 3] [--only-page]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import platform
import shutil
import socket
import sqlite3
import statistics
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any, TypeVar

import aiohttp
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.live.record import CycleRecord  # noqa: E402
from gateway.outputs.local_store import LocalStore  # noqa: E402
from gateway.scada.login_throttle import ThrottlePolicy  # noqa: E402
from gateway.scada.server import ScadaUser  # noqa: E402
from gateway.web.server import WebConsole, WebSettings  # noqa: E402

SENSORS = [f"T{i}" for i in range(1, 10)]
T = TypeVar("T")
USER = ("bench", "bench-secret")
AGAIN = 3  # Chromium loads after the first, each drawn afresh


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class StubGateway:
    """The parts of :class:`gateway.wiring.Gateway` the console reads."""

    def __init__(self, machines: list[str], store: Path) -> None:
        comp = SimpleNamespace(unit="mm", sign=1, axes=None)
        self.loops = [
            SimpleNamespace(
                config=SimpleNamespace(id=m, compensation=comp),
                compensation_enabled=True,
                cycles=0,
                promotions=SimpleNamespace(version=0),
            )
            for m in machines
        ]
        self.supervisors: dict[str, Any] = {}
        self.config = SimpleNamespace(logging=SimpleNamespace(influxdb=None, local_store=store))

    def health(self, machine_id: str) -> dict[str, Any]:
        return {"cycles": 1, "failed_writes": 0, "link_errors_total": 0}


def record(machine: str, t: float) -> CycleRecord:
    temps = {s: 25.0 + 0.1 * i + (t % 60) / 600 for i, s in enumerate(SENSORS)}
    return CycleRecord(
        machine=machine,
        time_s=t,
        temperatures_C=temps,
        quality=dict.fromkeys(SENSORS, "good"),
        quality_reasons={},
        speed_rpm=8000.0,
        regime="variable",
        model_id="mlr-error_um-variable",
        predicted_um=12.3,
        target_um=12.3,
        applied_um=12.1,
        written_cnc=0.0121,
        write_status="ok: tracking",
    )


async def machine_task(name: str, phase_s: float, stop_s: float, sink: Any, out: list) -> None:
    due = time.monotonic() + phase_s  # the loop's own clock rounds to whole ms
    while due < stop_s:
        await asyncio.sleep(max(due - time.monotonic(), 0))
        out.append(time.monotonic() - due)
        sink(record(name, time.time()))
        due += 1.0


async def measure(console: WebConsole, machines: list[str], window_s: float) -> list[float]:
    lateness: list[float] = []
    stop = time.monotonic() + window_s
    await asyncio.gather(
        *(
            machine_task(m, i / len(machines), stop, console.record, lateness)
            for i, m in enumerate(machines)
        )
    )
    return lateness


def browsers(url: str, n: int, seconds: float, ready: Any) -> None:
    """``n`` overview pages with their event streams, for ``seconds`` (another process)."""

    async def one(received: list[int]) -> None:
        jar = aiohttp.CookieJar(unsafe=True)
        async with aiohttp.ClientSession(cookie_jar=jar) as session:
            form = {"username": USER[0], "password": USER[1]}
            async with session.post(url + "/login", data=form) as response:
                await response.read()
            async with session.get(url + "/events") as stream:
                async for _ in stream.content:
                    received[0] += 1

    async def run() -> None:
        received = [0]
        tasks = [asyncio.create_task(one(received)) for _ in range(n)]
        await asyncio.sleep(3)
        ready.set()
        await asyncio.sleep(seconds)
        for task in tasks:
            task.cancel()

    asyncio.run(run())


def p(samples: list[float], q: float) -> float:
    ordered = sorted(samples)
    return ordered[min(int(q * len(ordered)), len(ordered) - 1)] * 1000


def summary(samples: list[float]) -> dict[str, float]:
    return {
        "cycles": len(samples),
        "median_ms": round(statistics.median(samples) * 1000, 2),
        "p99_ms": round(p(samples, 0.99), 2),
        "max_ms": round(max(samples) * 1000, 2),
    }


def fill_days(store: Path, machine: str, now_s: float, days: int = 1) -> float:
    """``days`` × 24 h of 1 Hz points of ``machine``, written in the earlier JSON layout
    and converted by opening the store (as a gateway's first start does); the seconds
    the conversion took."""
    from tests.json_layout_store import SCHEMA

    db = sqlite3.connect(store)
    db.executescript(SCHEMA)
    for day in range(days):
        _fill_day(db, machine, now_s - 86_400 * (days - 1 - day))
    db.close()
    started = time.perf_counter()
    LocalStore(store).close()
    return round(time.perf_counter() - started, 1)


def _fill_day(db: sqlite3.Connection, machine: str, now_s: float) -> None:
    rows = []
    for k in range(86_400):
        t = now_s - 86_400 + k
        ns = int(t * 1e9)
        growth = 10 + 8 * ((k % 7200) / 7200)
        fields = {
            "speed_rpm": 8000.0 if (k // 3600) % 2 else 3000.0,
            "predicted_um": growth,
            "applied_um": growth - 0.2,
            "written_cnc": (growth - 0.2) / 1000,
            "write_status": "ok: tracking",
            "link_errors": 0,
        }
        rows.append(
            ("spindle_cycle", machine, json.dumps({"machine": machine}), ns, json.dumps(fields))
        )
        for i, s in enumerate(SENSORS):
            tags = {"machine": machine, "sensor": s, "quality": "good"}
            value = {"value_C": 22 + i * 0.5 + growth / 5}
            rows.append(("spindle_temperature", machine, json.dumps(tags), ns, json.dumps(value)))
        if k % 120 == 0:
            rows.append(
                (
                    "spindle_probe",
                    machine,
                    json.dumps({"machine": machine}),
                    ns,
                    json.dumps({"error_um": growth + 1}),
                )
            )
    db.executemany("INSERT INTO points VALUES (?, ?, ?, ?, ?)", rows)
    db.commit()


async def page_load(url: str, machine: str, hours: int = 24) -> dict[str, float]:
    jar = aiohttp.CookieJar(unsafe=True)
    times = {}
    async with aiohttp.ClientSession(cookie_jar=jar) as session:
        form = {"username": USER[0], "password": USER[1]}
        async with session.post(url + "/login", data=form) as response:
            await response.read()
        for attempt in ("cold", "cached"):
            started = time.perf_counter()
            async with session.get(f"{url}/machines/{machine}?h={hours}") as response:
                await response.read()
            async with session.get(f"{url}/machines/{machine}/plot.svg?h={hours}") as response:
                svg = await response.read()
            times[f"http_{attempt}_s"] = round(time.perf_counter() - started, 3)
        times["svg_bytes"] = len(svg)
    return times


#: The first navigation's timing in the page (ms from its start): the page's HTML
#: received, the plot's SVG received.
_TIMING = """
const n = performance.getEntriesByType('navigation')[0];
const r = performance.getEntriesByType('resource').filter(e => e.name.includes('plot.svg'))[0];
return [n.responseEnd, r ? r.responseEnd : null];
"""


def chromium_load(
    url: str, machine: str, hours: int = 24, clear: Callable[[], None] | None = None
) -> dict[str, Any] | None:
    """The page in headless Chromium, from navigation until its plot image is complete:
    first in a new browser (``chromium_s``), then ``AGAIN`` times in the same browser,
    each after ``clear`` (the console's drawn results forgotten: read and drawn afresh),
    and when the first one's HTML and SVG arrived."""
    if shutil.which("chromium") is None or shutil.which("chromedriver") is None:
        return None
    sys.path.insert(0, str(ROOT))
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    from tests.browser import chromium

    driver = chromium()
    try:
        driver.get(url + "/login")
        driver.find_element(By.ID, "username").send_keys(USER[0])
        driver.find_element(By.ID, "password").send_keys(USER[1])
        driver.find_element(By.ID, "login").click()
        # the session cookie is set once the login's answer arrived: a page asked for
        # before that is the login page again (seen under full contention)
        WebDriverWait(driver, 30).until(lambda d: "/login" not in d.current_url)
        loads, timing = [], None
        for k in range(1 + AGAIN):
            if k and clear is not None:
                clear()
            started = time.perf_counter()
            driver.get(f"{url}/machines/{machine}?h={hours}")
            found = WebDriverWait(driver, 30).until(lambda d: d.find_elements(By.ID, "plot"))
            plot = found[0]
            while not driver.execute_script("return arguments[0].complete", plot):
                time.sleep(0.02)
            loads.append(round(time.perf_counter() - started, 3))
            if k == 0:
                timing = [
                    round(x) if x is not None else None for x in driver.execute_script(_TIMING)
                ]
        return {
            "chromium_s": loads[0],
            "chromium_again_s": loads[1:],
            "chromium_html_and_svg_ms": timing,
        }
    finally:
        driver.quit()


async def main_async(args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    machines = [f"m{i:03d}" for i in range(args.machines)]
    store = folder / "points.sqlite"
    converted_s = None
    if args.store is not None:
        store = args.store
    else:
        converted_s = fill_days(store, machines[0], time.time(), args.days)
    port = free_port()
    settings = WebSettings(
        host="127.0.0.1",
        port=port,
        users=[ScadaUser(USER[0], USER[1], "viewer")],
        throttle=ThrottlePolicy(),
    )
    console = WebConsole(settings, StubGateway(machines, store))  # type: ignore[arg-type]
    await console.start()
    url = f"http://127.0.0.1:{port}"
    try:
        if args.only_page:
            page = await machine_page(console, url, machines[0], store, args.hours)
            return {"converted_s": converted_s, f"machine_page_{args.hours}h_1hz": page}
        await measure(console, machines, 3.0)  # warm-up
        alone = [await measure(console, machines, args.window_s)]
        watched = []
        for _ in range(args.rounds):
            window = lambda: measure(console, machines, args.window_s)  # noqa: E731
            watched.append(await with_browsers(url, args, window))
            alone.append(await measure(console, machines, args.window_s))
        page = await machine_page(console, url, machines[0], store)
    finally:
        await console.stop()
    pooled_alone = [x for window in alone for x in window]
    pooled_watched = [x for window in watched for x in window]
    return {
        "windows": [
            {"browsers": 0 if k % 2 == 0 else args.browsers, **summary(w)}
            for k, w in enumerate(_interleave(alone, watched))
        ],
        "p99_ms_without": round(p(pooled_alone, 0.99), 2),
        f"p99_ms_with_{args.browsers}": round(p(pooled_watched, 0.99), 2),
        "p99_ratio": round(p(pooled_watched, 0.99) / p(pooled_alone, 0.99), 3),
        "p99_ratio_per_round": [
            round(p(w, 0.99) / p(alone[k] + alone[k + 1], 0.99), 3) for k, w in enumerate(watched)
        ],
        "machine_page_24h_1hz": page,
    }


async def machine_page(
    console: WebConsole, url: str, machine: str, store: Path, hours: int = 24
) -> dict:
    """The page of the last ``hours`` over HTTP (cold, cached), in Chromium (cold), and
    its read and drawing timed alone in this process."""
    console.renderer.clear()
    page = await page_load(url, machine, hours)
    console.renderer.clear()  # the browser's first load is drawn afresh too
    loop = asyncio.get_running_loop()

    def clear() -> None:  # from the browser's thread, on the console's loop
        asyncio.run_coroutine_threadsafe(_cleared(console), loop).result()

    browser = await loop.run_in_executor(None, chromium_load, url, machine, hours, clear)
    return {**page, **(browser or {"chromium_s": None}), **read_and_draw(store, machine, hours)}


async def _cleared(console: WebConsole) -> None:
    console.renderer.clear()


def read_and_draw(store: Path, machine: str, hours: int = 24) -> dict[str, float]:
    from gateway.web import plots, series

    plots.proposal_svg(np.zeros(0), np.zeros(0), 1.0, 1.0)  # matplotlib imported before
    now = time.time()
    clocks = [(time.perf_counter(), time.process_time())]
    data = series.machine_view(("local", str(store)), machine, now - 3600 * hours, now, 1000.0)
    clocks.append((time.perf_counter(), time.process_time()))
    plots.machine_svg(data, machine)
    clocks.append((time.perf_counter(), time.process_time()))
    (w0, c0), (w1, c1), (w2, c2) = clocks
    return {
        "alone_read_s": round(w1 - w0, 3),
        "alone_read_cpu_s": round(c1 - c0, 3),
        "alone_draw_s": round(w2 - w1, 3),
        "alone_draw_cpu_s": round(c2 - c1, 3),
    }


def _interleave(alone: list, watched: list) -> list:
    out = [alone[0]]
    for w, a in zip(watched, alone[1:], strict=True):
        out += [w, a]
    return out


async def with_browsers(
    url: str, args: argparse.Namespace, window: Callable[[], Awaitable[T]]
) -> T:
    """``window()`` measured while ``args.browsers`` overviews are open (another process)."""
    ready = multiprocessing.get_context("spawn").Event()
    watchers = multiprocessing.get_context("spawn").Process(
        target=browsers, args=(url, args.browsers, args.window_s + 5, ready)
    )
    watchers.start()
    while not ready.is_set():
        await asyncio.sleep(0.1)
    measured = await window()
    while watchers.is_alive():
        await asyncio.sleep(0.2)
    return measured


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--machines", type=int, default=200)
    parser.add_argument("--browsers", type=int, default=20)
    parser.add_argument("--window-s", type=float, default=30.0)
    parser.add_argument("--rounds", type=int, default=3, help="windows with browsers")
    parser.add_argument("--only-page", action="store_true", help="the machine page part only")
    parser.add_argument("--days", type=int, default=1, help="days of 1 Hz points in the store")
    parser.add_argument(
        "--store", type=Path, default=None, help="serve this store (machine m000) instead"
    )
    parser.add_argument("--hours", type=int, default=24, help="the machine page's window")
    args = parser.parse_args()
    import uvloop

    with tempfile.TemporaryDirectory() as tmp:
        result = uvloop.run(main_async(args, Path(tmp)))
    result["machine"] = {"cpus": os.cpu_count(), "python": platform.python_version()}
    result["args"] = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
