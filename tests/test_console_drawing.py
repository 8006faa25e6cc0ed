"""The machine page's drawing: answered before its plot is drawn, local time across a
change of the UTC offset, and a month of probes as lines.

Real parts: the console serves over real HTTP from a local store written the way the
gateway writes it; the drawing is matplotlib's own SVG, its elements counted.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import numpy as np
import pytest

from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import points_from_record, probe_point
from gateway.web.plots import LocalDays, machine_svg
from gateway.web.series import COLUMNS, MachineView
from tests.test_timeseries import make_records
from tests.test_web_auth import OPERATOR, console_of


def test_the_page_is_answered_with_its_plot_already_being_drawn(tmp_path: Path) -> None:
    """The page needs the window's events, not its plot: it is answered once the window
    is read, and the plot the browser asks for next is drawn from that same read,
    started before the page went out."""
    now = time.time()
    records = make_records("m1", 600)
    with LocalStore(tmp_path / "points.sqlite") as store:
        points = [p for r in records for p in points_from_record(r, now - 600)]
        store.write([*points, probe_point("m1", 300, 4.0, now - 600)])

    async def scenario() -> tuple[bool, bool, str, int]:
        async with console_of(["m1"], tmp_path) as console:
            url = console.url.rstrip("/")
            async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as client:
                form = {"username": OPERATOR.username, "password": OPERATOR.password}
                async with client.post(url + "/login", data=form) as response:
                    await response.read()
                async with client.get(url + "/machines/m1?h=1") as page:
                    html = await page.text()
                key = ("machine-plot", "m1", 1)
                renderer = console.renderer
                ahead = key in renderer._pending or key in renderer._cache
                read_once = ("machine", "m1", 1) in renderer._cache
                async with client.get(url + "/machines/m1/plot.svg?h=1") as plot:
                    svg = await plot.text()
                return ahead, read_once, svg, html.count("plot.svg")

    ahead, read_once, svg, images = asyncio.run(scenario())
    assert images == 1
    assert ahead, "the plot was not being drawn when the page went out"
    assert read_once
    assert "m1: last 1 h (600 cycles)" in svg and "probe error (µm)" in svg


@pytest.fixture
def berlin() -> Iterator[None]:
    before = os.environ.get("TZ")
    os.environ["TZ"] = "Europe/Berlin"
    time.tzset()
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("TZ")
        else:
            os.environ["TZ"] = before
        time.tzset()


def test_local_time_follows_the_clock_across_the_end_of_summer_time(berlin: None) -> None:
    # 2026-10-25: 03:00 CEST (UTC+2) becomes 02:00 CET (UTC+1), at 01:00 UTC
    change_s = 1792890000.0
    window = (change_s - 6 * 3600, change_s + 6 * 3600)
    days = LocalDays(window)
    t = np.array([change_s - 1800, change_s + 1800])  # 02:30 CEST, 02:30 CET
    local = days(t) * 86_400
    assert local.tolist() == pytest.approx([t[0] + 7200, t[1] + 3600])
    at, labels = days.ticks(window)
    # whole local hours, labelled as the wall clock reads them
    assert np.allclose(np.round(at * 24), at * 24)
    assert labels[0] == "22:00\n24 Oct"  # 21:00 CEST is the start; steps of 2 h
    assert "00:00\n25 Oct" in labels
    summer = LocalDays((change_s - 7200, change_s - 3600))
    assert summer(np.array([change_s - 3600])) * 86_400 == pytest.approx(change_s + 3600)


def _view(probes: int, span_s: float) -> MachineView:
    t = np.linspace(0.0, span_s, probes) + 1.8e9
    empty = (np.zeros(0), np.zeros(0))
    lines = dict.fromkeys(("speed_rpm", "predicted_um", "applied_um", "cnc_um"), empty)
    return MachineView(
        cycles=0,
        lines={**lines, "correction_um": empty},
        temperatures_C={},
        probe_t_s=t,
        probe_error_um=np.sin(t / 3600.0) * 5,
        probe_residual_um=np.cos(t / 3600.0),
        events=[],
        quality_changes=[],
        window_s=(1.8e9, 1.8e9 + span_s),
    )


def test_a_month_of_probes_is_drawn_as_lines_and_a_day_of_them_as_markers() -> None:
    """A marker is an element of its own in the SVG: 3600 probes (a month's column
    extremes) would be 7200 of them; as lines they are two paths."""
    month = machine_svg(_view(4 * COLUMNS, 30 * 86_400.0), "m1")
    day = machine_svg(_view(COLUMNS // 2, 86_400.0), "m1")
    assert day.count("<use ") >= 2 * (COLUMNS // 2)
    assert month.count("<use ") < 50  # the legend's and the ticks' marks only
    assert "probe measured" in month and "residual" in month
    assert len(month) < len(day) + 200_000
