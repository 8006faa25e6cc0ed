"""A multi-axis machine in the operator console: each axis's values and plots.

The console runs in this process (its own event loop in a thread) over a stand-in of
the gateway (no machines cycle: their configuration and the records the console is
handed); its logged window is a real local store the 3-axis machine's points were
written to as the gateway writes them. Headless Chromium logs in over loopback HTTP and
reads the overview and the machine page; the plot is the SVG the page loads.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from selenium.webdriver.common.by import By

from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import points_from_record
from gateway.scada.login_throttle import ThrottlePolicy
from gateway.scada.server import ScadaUser
from gateway.web.series import machine_view
from gateway.web.server import WebConsole, WebSettings
from tests.browser import chromium
from tests.ports import free_tcp_port
from tests.records import axes_record, written_record
from tests.test_web_browser_security import submit_login

VIEWER = ScadaUser("vera", "view-secret-8", "viewer")
MULTI, SINGLE = "vmc-3", "vmc-1"
#: Z in mm, X in µm with the opposite sign, Y in mm: each axis's own unit and sign
AXES = {
    "Z": SimpleNamespace(macro=500, unit="mm", sign=1),
    "X": SimpleNamespace(macro=502, unit="um", sign=-1),
    "Y": SimpleNamespace(macro=504, unit="mm", sign=1),
}


def applied(n: int) -> dict[str, float]:
    """Cycle ``n``'s compensation per axis (µm): Z rises, X falls, Y stays near 5."""
    return {"Z": 0.01 * n, "X": -0.02 * n, "Y": 5.0 + 0.001 * n}


def multi_record(n: int, stamp_s: float) -> Any:
    record = axes_record(MULTI, float(n), {"T1": 25.0 + 0.001 * n}, applied(n), stamp_s=stamp_s)
    record.axes["X"].written_cnc = -record.axes["X"].applied_um  # µm, sign -1
    record.axes["Y"].write_status = "no write: holding for 5 s (2 s so far)"
    return record


def gateway(tmp_path: Path) -> Any:
    """What the console reads of a gateway: its loops' ids and settings (no cycles run)."""

    def loop(machine: str, axes: dict[str, Any]) -> Any:
        comp = SimpleNamespace(unit="mm", sign=1, axes=axes)
        return SimpleNamespace(
            config=SimpleNamespace(id=machine, compensation=comp),
            compensation_enabled=True,
            cycles=0,
            promotions=SimpleNamespace(version=0),
        )

    logging = SimpleNamespace(influxdb=None, local_store=tmp_path / "points.sqlite")
    return SimpleNamespace(
        loops=[loop(MULTI, AXES), loop(SINGLE, {})],
        supervisors={},
        config=SimpleNamespace(logging=logging),
        health=lambda machine: {"cycles": 0},
    )


class Served:
    """The console started in a thread's event loop; ``url`` without a trailing slash."""

    def __init__(self, tmp_path: Path) -> None:
        settings = WebSettings(
            host="127.0.0.1",
            port=free_tcp_port(),
            users=[VIEWER],
            throttle=ThrottlePolicy(max_failures=5, window_s=60, lockout_s=30),
            tick_s=0.1,
        )
        self.console = WebConsole(settings, gateway(tmp_path))
        self.url = self.console.url.rstrip("/")
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()
        self.call(self.console.start())

    def call(self, work: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(work, self.loop).result(timeout=60)

    def record(self, record: Any) -> None:
        self.loop.call_soon_threadsafe(self.console.record, record)

    def close(self) -> None:
        self.call(self.console.stop())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout=10)
        self.loop.close()


def log_points(path: Path, records: list[Any]) -> None:
    with LocalStore(path) as store:
        store.write([p for r in records for p in points_from_record(r)])


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    now = time.time()
    records = [multi_record(n, now - 600 + n) for n in range(590)]
    log_points(tmp_path / "points.sqlite", records)
    server = Served(tmp_path)
    try:
        server.record(records[-1])
        server.record(written_record(SINGLE, 1.0, {"T1": 24.0}, 3.0))
        yield server
    finally:
        server.close()


def test_machine_view_keeps_each_axis_apart_and_the_main_lines_are_the_first(
    tmp_path: Path,
) -> None:
    """Logged to the local store, read back: the first axis with the untagged rows
    logged before the machine had several axes, each axis its own lines."""
    start = 1_780_000_000.0
    before = [written_record(MULTI, 0.0, {"T1": 25.0}, -7.0, stamp_s=start + n) for n in range(10)]
    after = [multi_record(n, start + n) for n in range(10, 300)]
    for record in after[190:]:  # from cycle 200 the Y macro's read-back disagrees
        record.axes["Y"].write_status = "refused: read-back differs"
    path = tmp_path / "points.sqlite"
    log_points(path, before + after)
    factors = {"Z": 1000.0, "X": -1.0, "Y": 1000.0}
    for aggregate in (True, False):
        view = machine_view(
            ("local", str(path)), MULTI, start, start + 300, 1000.0, 60, aggregate, factors
        )
        assert view.cycles == 300  # 10 untagged + 290 of the first axis, none of X or Y
        _, predicted = view.lines["predicted_um"]
        assert np.nanmin(predicted) == -7.0 and np.nanmax(predicted) == pytest.approx(2.99)
        assert list(view.axis_lines) == ["Z", "X", "Y"]
        for axis in factors:
            t, y = view.axis_lines[axis]["applied_um"]
            assert len(t) == 2 * 58  # 5 s columns 2..59 of 60 hold its cycles, two points each
            expected = [applied(n)[axis] for n in range(10, 300)]
            assert np.min(y) == pytest.approx(min(expected))
            assert np.max(y) == pytest.approx(max(expected))
            cnc = view.axis_lines[axis]["cnc_um"][1]
            assert np.max(cnc) == pytest.approx(max(expected))  # the axis's unit and sign
        refusals = [e for e in view.events if e[1].startswith("write")]
        assert refusals == [(start + 200, "write (Y)", "refused: read-back differs")]


#: The overview's axis entries matching a selector: (axis, text shown, held), in one read.
_AXES = """return [...document.querySelectorAll(arguments[0])].map(
    s => [s.dataset.axis, s.innerText.trim(), s.classList.contains('held')]);"""


def test_the_page_shows_each_axis_and_plots_it_and_the_overview_lists_them(
    served: Served,
) -> None:
    driver = chromium()
    try:
        submit_login(driver, served.url, VIEWER.username, VIEWER.password)
        driver.get(served.url + f"/machines/{MULTI}")
        rows = driver.find_elements(By.CSS_SELECTOR, "table#axes tbody tr")
        cells = {
            r.get_attribute("data-axis"): [c.text for c in r.find_elements(By.TAG_NAME, "td")]
            for r in rows
        }
        held = [r.get_attribute("data-axis") for r in rows if "held" in r.get_attribute("class")]
        driver.get(served.url + f"/machines/{MULTI}/plot.svg?h=1")
        svg = driver.page_source
        driver.get(served.url + f"/machines/{SINGLE}")
        single_tables = driver.find_elements(By.CSS_SELECTOR, "table#axes")
        driver.get(served.url + "/")
        # read in one script: the live stream may redraw the rows between two reads
        overview = [tuple(a) for a in driver.execute_script(_AXES, f"#row-{MULTI} .axes .axis")]
        single_axes = driver.execute_script(_AXES, f"#row-{SINGLE} .axes .axis")
        served.record(multi_record(1000, time.time()))  # the live stream updates the axes
        first = f"#row-{MULTI} .axes .axis[data-axis='Z']"
        deadline = time.monotonic() + 20
        while [a[1] for a in driver.execute_script(_AXES, first)] != ["Z 10.0 / 10.0"]:
            assert time.monotonic() < deadline, "the overview's axes not updated within 20 s"
            time.sleep(0.1)
    finally:
        driver.quit()
    last = applied(589)
    assert list(cells) == ["Z", "X", "Y"]
    assert cells["Z"] == ["Z", "#500", "lag-ridge-Z", "5.9", "1.0", "5.9", "0.006", "ok"]
    assert cells["X"][:6] == ["X", "#502", "lag-ridge-X", "-11.8", "1.5", "-11.8"]
    assert cells["X"][6] == "11.78"
    assert cells["Y"][3] == f"{last['Y']:.1f}" and cells["Y"][5] == f"{last['Y']:.1f}"
    assert cells["Y"][7] == "held: no write: holding for 5 s (2 s so far)"
    assert held == ["Y"]
    for axis in ("Z", "X", "Y"):
        assert f"{axis} compensation (µm)" in svg, axis
    assert overview == [("Z", "Z 5.9 / 5.9", False), ("X", "X -11.8 / -11.8", False),
                        ("Y", "Y 5.6 / 5.6", True)]  # fmt: skip
    assert not single_tables and not single_axes
