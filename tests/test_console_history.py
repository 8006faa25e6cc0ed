"""Long machine-page windows read from the local store's per-minute history.

Real parts: cycle records become points as the gateway makes them and go into the
local store, which closes its 10-minute periods into Parquet parts with their
per-minute history; the last period stays open (1-s rows in segment files). A 3 h
window read through the history gives, per plot column, exactly the lowest and highest
values of reading every row, and the same events; with the 1-s rows aged out the
30-day page still plots the history, in headless Chromium.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from types import SimpleNamespace

import duckdb
import numpy as np
import pytest
from selenium.webdriver.common.by import By

from gateway.outputs import store_parts
from gateway.outputs.local_store import LocalStore, history_folder, parts_folder
from gateway.outputs.points import NS_PER_S, points_from_record, probe_point
from gateway.web import series, store_history
from gateway.web.series import HISTORY_FROM_S, machine_view, read_machine
from tests.browser import chromium
from tests.test_console_axes import SINGLE, VIEWER, Served
from tests.test_timeseries import EPOCH_S, make_records
from tests.test_web_browser_security import submit_login
from tests.test_web_console import _login, session

CYCLES = 8 * 3600 + 420  # 8 h 7 min: the last period stays open
COLUMNS = 90  # 8 h 7 min in 90 columns: 6 minutes a column
SPIKES = {5000: 95.0, 5001: -40.0, 9001: 120.0}  # T1, °C


def _points(epoch_s: float, machine: str = "m1") -> list:
    records = make_records(machine, CYCLES, sensors=("T1", "T2", "T3"))
    for i, value in SPIKES.items():
        records[i].temperatures_C["T1"] = value
    records[4000].write_status = "refused: readback differs"
    records[6000].write_status = "hold: external change of #500"
    points = [p for record in records for p in points_from_record(record, epoch_s)]
    return points + [
        probe_point(machine, t, 5.0 + t / 1000, epoch_s) for t in range(0, CYCLES, 120)
    ]


def _fill(path: Path, epoch_s: float, machine: str = "m1") -> None:
    with LocalStore(path) as local:
        local.write(_points(epoch_s, machine))
        local.compact(int((epoch_s + CYCLES) * NS_PER_S))


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("history") / "points.sqlite"
    _fill(path, EPOCH_S)
    assert list(history_folder(path).glob("*.parquet"))  # closed periods have a history
    assert list(path.with_name(path.name + ".open").glob("*.log"))  # the last is open
    return path


def _columns(t_s: np.ndarray, y: np.ndarray, start_ns: int, width_ns: int) -> dict:
    """Per column index its lowest and highest finite value."""
    keep = np.isfinite(y)
    column = ((np.round(t_s[keep] * NS_PER_S).astype(np.int64) - start_ns) // width_ns).tolist()
    found: dict[int, list[float]] = {}
    for k, v in zip(column, y[keep].tolist(), strict=True):
        low, high = found.get(k, [v, v])
        found[k] = [min(low, v), max(high, v)]
    return found


def test_the_history_gives_each_columns_lowest_and_highest_of_every_row(store: Path) -> None:
    window = (EPOCH_S, EPOCH_S + CYCLES)
    assert window[1] - window[0] >= HISTORY_FROM_S  # the page reads this from the history
    spec = ("local", str(store))
    view = machine_view(spec, "m1", *window, 1000.0, COLUMNS)
    full = read_machine(spec, "m1", *window, 1000.0)
    _, start_ns, width_ns = series.history_window_of(store, "m1", window, COLUMNS)
    assert width_ns == 6 * 60 * NS_PER_S and start_ns == int(EPOCH_S * NS_PER_S)
    every = {
        "speed_rpm": full.speed_rpm,
        "predicted_um": full.predicted_um,
        "applied_um": full.applied_um,
        "cnc_um": full.cnc_um,
    }
    for name, values in every.items():
        expected = _columns(full.t_s, values, start_ns, width_ns)
        assert _columns(*view.lines[name], start_ns, width_ns) == expected, name
        assert len(expected) == 82  # the columns holding cycles (8 h 7 min)
    assert sorted(view.temperatures_C) == sorted(full.temperatures_C)
    for sensor, (t_s, value_C) in full.temperatures_C.items():
        expected = _columns(t_s, value_C, start_ns, width_ns)
        assert _columns(*view.temperatures_C[sensor], start_ns, width_ns) == expected, sensor
    assert {95.0, -40.0, 120.0} <= set(view.temperatures_C["T1"][1].tolist())
    assert view.cycles == full.cycles == CYCLES
    assert view.events == series.events(full)
    assert view.quality_changes == full.quality_changes
    probes = (view.probe_t_s, view.probe_error_um)
    assert len(probes[0]) < len(full.probe_t_s)  # a column's extremes kept
    expected = _columns(full.probe_t_s, full.probe_error_um, start_ns, width_ns)
    assert _columns(*probes, start_ns, width_ns) == expected


def test_the_30_day_page_plots_the_history_once_the_1s_rows_aged_out(tmp_path: Path) -> None:
    path = tmp_path / "points.sqlite"
    epoch_s = (time.time() - 3 * 86_400) // 60 * 60
    _fill(path, epoch_s, SINGLE)
    spec = ("local", str(path))
    full = read_machine(spec, SINGLE, epoch_s, epoch_s + CYCLES, 1000.0)
    with LocalStore(path) as local:
        local.delete_before(int(time.time() * NS_PER_S))  # every 1-s row gone
    assert not list(parts_folder(path).glob("*.parquet"))
    now = time.time()
    view = machine_view(spec, SINGLE, now - 720 * 3600, now, 1000.0)
    assert read_machine(spec, SINGLE, now - 720 * 3600, now, 1000.0).cycles == 0
    assert CYCLES - 600 <= view.cycles < CYCLES  # the open period (under 10 min) went too
    closed = full.t_s < full.t_s[view.cycles]  # the cycles in the history
    for name in ("speed_rpm", "predicted_um", "applied_um"):
        _, y = view.lines[name]
        logged = getattr(full, name)[closed]
        assert (y.min(), y.max()) == (np.nanmin(logged), np.nanmax(logged)), name
    assert {95.0, -40.0} <= set(view.temperatures_C["T1"][1].tolist())  # the spikes
    served = Served(tmp_path)
    driver = chromium()
    try:
        submit_login(driver, served.url, VIEWER.username, VIEWER.password)
        driver.get(served.url + f"/machines/{SINGLE}?h=720")
        windows = [a.text for a in driver.find_elements(By.CSS_SELECTOR, "a.window")]
        plot = driver.find_element(By.ID, "plot")
        deadline = time.monotonic() + 60
        while not driver.execute_script("return arguments[0].complete", plot):
            assert time.monotonic() < deadline, "the 30-day plot not shown within 60 s"
            time.sleep(0.05)
        width = driver.execute_script("return arguments[0].naturalWidth", plot)
        driver.get(served.url + f"/machines/{SINGLE}/plot.svg?h=720")
        month = driver.page_source
        driver.get(served.url + f"/machines/{SINGLE}/plot.svg?h=1")
        hour = driver.page_source  # nothing logged in the last hour
    finally:
        driver.quit()
        served.close()
    assert windows == ["last 1 h", "last 8 h", "last 24 h", "last 30 days"]
    assert width > 0
    # a panel's legend is drawn only when it has lines
    assert month.count('id="legend_') == 4 and 'id="legend_' not in hour


def test_from_influxdb_the_30_day_window_is_refused(tmp_path: Path) -> None:
    """InfluxDB has no per-minute history here: its 30 days would be read row by row."""
    served = Served(tmp_path)
    logging = served.console.backend._gateway.config.logging
    logging.influxdb = SimpleNamespace(
        url_value=lambda: "http://127.0.0.1:9",
        token=lambda: "t",
        org_value=lambda: "o",
        bucket_value=lambda: "b",
        timeout_s=1.0,
    )
    user = (VIEWER.username, VIEWER.password)

    async def get(path: str) -> tuple[int, str]:
        async with session() as client:
            await _login(client, served.url, user)
            async with client.get(served.url + path) as response:
                return response.status, await response.text()

    try:
        status, text = asyncio.run(get(f"/machines/{SINGLE}?h=720"))
    finally:
        served.close()
    assert status == 400 and text == "h must be one of (1, 8, 24)"


def test_the_events_are_the_same_read_by_time_ranges_or_by_a_list_of_buckets(
    store: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The buckets where a write status may change are read as time ranges (pruned to
    their own row groups), or, past ``MAX_RANGES`` runs of them, as one span and a
    list: both give the events of reading every row."""
    window = (EPOCH_S, EPOCH_S + CYCLES)
    spec = ("local", str(store))
    by_ranges = machine_view(spec, "m1", *window, 1000.0, COLUMNS).events
    monkeypatch.setattr(store_history, "MAX_RANGES", 0)
    by_list = machine_view(spec, "m1", *window, 1000.0, COLUMNS).events
    every = series.events(read_machine(spec, "m1", *window, 1000.0))
    kinds = {kind for _, kind, _ in every}
    assert {"source fault", "reconnected", "sensor flag"} <= kinds
    assert by_ranges == by_list == every


def test_sparse_write_refusals_are_each_found_in_their_own_time_range(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A day of steady writing with three refusals hours apart: three separate runs of
    buckets are read, each as its own time range, and the events are those of every row."""
    records = make_records("m1", CYCLES, sensors=("T1", "T2"))
    for record in records:
        record.link_errors = []
        record.quality = dict.fromkeys(record.quality, "good")
    refused = (2000, 14_000, 26_000)
    for i in refused:
        records[i].write_status = "refused: readback differs"
    path = tmp_path / "points.sqlite"
    with LocalStore(path) as local:
        local.write([p for record in records for p in points_from_record(record, EPOCH_S)])
        local.compact(int((EPOCH_S + CYCLES) * NS_PER_S))
    spec, window = ("local", str(path)), (EPOCH_S, EPOCH_S + CYCLES)
    read: list[str] = []
    ranges = store_history._bucket_ranges

    def recorded(buckets: list[int]) -> str:
        read.append(ranges(buckets))
        return read[-1]

    monkeypatch.setattr(store_history, "_bucket_ranges", recorded)
    view = machine_view(spec, "m1", *window, 1000.0, COLUMNS)
    assert read and read[0].count(" OR ") >= 2  # the first bucket and each refusal's
    every = series.events(read_machine(spec, "m1", *window, 1000.0))
    writes = sorted(t - EPOCH_S for t, kind, _ in view.events if kind == "write")
    assert writes == [float(i) for i in refused]
    assert view.events == every


def test_a_history_written_before_the_write_states_gives_the_same_page(
    store: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The first 4 h closed with a history that keeps no write state (as one written
    before it did), the rest with it: the page's lines and events are those of the store
    whose history has the states throughout, and those of reading every row."""
    without = store_parts.HISTORY_SELECT.rsplit(", min(", 1)[0]
    assert "write_state" in store_parts.HISTORY_SELECT and "write_state" not in without
    assert "speed_rpm_min" in without
    path = tmp_path / "points.sqlite"
    points = _points(EPOCH_S)
    half = int((EPOCH_S + 4 * 3600) * NS_PER_S)
    with LocalStore(path) as local:
        monkeypatch.setattr(store_parts, "HISTORY_SELECT", without)
        local.write([p for p in points if p.time_ns < half])
        local.compact(half)
        monkeypatch.undo()
        local.write([p for p in points if p.time_ns >= half])
        local.compact(int((EPOCH_S + CYCLES) * NS_PER_S))
    kinds = [
        "write_state_min" in {c for (c, *_) in duckdb.sql(f"DESCRIBE FROM '{f}'").fetchall()}
        for f in sorted(history_folder(path).glob("*.parquet"))
    ]
    assert True in kinds and False in kinds, kinds  # both kinds of history file
    window = (EPOCH_S, EPOCH_S + CYCLES)
    monkeypatch.setattr(series, "MAX_EVENTS", 10**6)  # every event compared, not the newest
    mixed = machine_view(("local", str(path)), "m1", *window, 1000.0, COLUMNS)
    stated = machine_view(("local", str(store)), "m1", *window, 1000.0, COLUMNS)
    every = series.events(read_machine(("local", str(path)), "m1", *window, 1000.0))
    assert mixed.events == stated.events == every
    assert {kind for _, kind, _ in every} >= {"source fault", "reconnected", "sensor flag"}
    early = {kind for t, kind, _ in every if t < half / NS_PER_S and kind != "sensor flag"}
    assert {"source fault", "reconnected"} <= early, early  # changes in the older history
    for name, (t_s, values) in stated.lines.items():
        assert np.array_equal(mixed.lines[name][0], t_s), name
        assert np.array_equal(mixed.lines[name][1], values, equal_nan=True), name
