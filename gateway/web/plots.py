"""Server-side plots as SVG (matplotlib), drawn in a worker process off the event loop.

The machine page draws :func:`gateway.web.series.machine_view`: each line already cut
to a min/max envelope per pixel column of the window (24 h of 1 Hz data, 86 400
points a series, becomes at most two points per column, every spike still visible).
Reading and drawing run in one spawned worker process (:class:`PlotRenderer`), so
neither holds the gateway's interpreter; they are two jobs, so the page (which needs
the window's events) is answered once the window is read while its plot is drawn, and
the browser's request for the plot meets the drawing under way. The newest result of
each is kept for ``cache_s``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import io
import multiprocessing
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np

from gateway.web.series import (
    COLUMNS,
    MachineView,
    Series,
    SourceSpec,
    machine_view,
    read_probes,
)

#: Steps of the machine page's time ticks (hours): the first giving at most
#: ``MAX_TICKS`` ticks over the plot (1 h: every 10 min ... 30 days: every 5 days; a
#: machine logging for a minute: every 10 s).
TICK_STEPS_H = (
    *(s / 3600 for s in (10, 30, 60, 120, 300, 600, 900, 1800)),
    *(1, 2, 3, 6, 12, 24, 48, 72, 120, 168),
)
MAX_TICKS = 8
SECONDS_PER_DAY = 86_400.0
#: matplotlib settings of the machine page's SVG (:func:`machine_svg`)
SVG_STYLE: dict[str, Any] = {"svg.fonttype": "none", "path.simplify_threshold": 0.5}


def _dates(t: np.ndarray) -> list[datetime]:
    return [datetime.fromtimestamp(float(x)) for x in t]


class LocalDays:
    """Unix seconds as matplotlib's date numbers (days since 1970) of local time.

    The machine page hands matplotlib plain floats and places its own ticks: a list of
    ``datetime`` objects per line, converted back by matplotlib's units machinery, and
    the automatic date ticks worked out anew on every shared panel, were about a third
    of the drawing. Local time is the clock on the shop floor; a window across a change
    of the UTC offset (summer time) converts each point on its own."""

    def __init__(self, span_s: tuple[float, float]) -> None:
        start, stop = span_s
        offsets = {time.localtime(start).tm_gmtoff, time.localtime(stop).tm_gmtoff}
        self.offset_s = offsets.pop() if len(offsets) == 1 else None

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        if self.offset_s is not None:
            return (t + self.offset_s) / SECONDS_PER_DAY
        offsets = np.array([time.localtime(x).tm_gmtoff for x in t.tolist()], dtype=float)
        return (t + offsets) / SECONDS_PER_DAY

    def ticks(self, span_s: tuple[float, float]) -> tuple[np.ndarray, list[str]]:
        """Ticks on whole local steps over the span, and their labels."""
        low, high = self(np.asarray(span_s))
        span_h = (high - low) * 24
        step_h = next((h for h in TICK_STEPS_H if span_h / h <= MAX_TICKS), TICK_STEPS_H[-1])
        step = step_h / 24
        at = np.arange(np.ceil(low / step) * step, high, step)
        pattern = "%d %b" if step_h >= 24 else "%H:%M:%S" if step_h < 1 / 60 else "%H:%M"
        stamps = np.round(at * SECONDS_PER_DAY).astype(np.int64)
        labels = [time.strftime(pattern, time.gmtime(int(x))) for x in stamps]
        if step_h < 24:  # the day under each midnight and under the first tick
            labels = [
                time.strftime(f"{pattern}\n%d %b", time.gmtime(int(x)))
                if k == 0 or x % 86_400 == 0
                else label
                for k, (x, label) in enumerate(zip(stamps, labels, strict=True))
            ]
        return at, labels


def _extent_of(data: MachineView) -> tuple[float, float]:
    """The span the plot shows: from the first to the last time logged in the window
    (a machine that started ten minutes ago fills the plot's width), else the window."""
    found = [t for t, _ in [*data.lines.values(), *data.temperatures_C.values()] if len(t)]
    if len(data.probe_t_s):
        found.append(np.asarray(data.probe_t_s))
    if found:
        first = min(float(np.min(t)) for t in found)
        last = max(float(np.max(t)) for t in found)
        if last > first:
            margin = 0.02 * (last - first)
            return first - margin, last + margin
    if data.window_s is not None:
        return data.window_s
    now = time.time()
    return now - 3600.0, now


class _Panel:
    """One panel of the machine page and the clock its times are drawn in."""

    def __init__(self, ax: Any, days: LocalDays) -> None:
        self.ax, self.days = ax, days

    def line(self, series: tuple[np.ndarray, np.ndarray], label: str, **style: Any) -> None:
        t, y = series
        if len(t):
            self.ax.plot(self.days(t), y, label=label, linewidth=0.9, **style)


def _figure(rows: int, span_s: tuple[float, float]) -> tuple[Any, list[_Panel]]:
    """The panels, one above the other, sharing a time axis with fixed ticks."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FixedFormatter, FixedLocator

    # Fixed margins: a constrained layout measures every label once more before
    # drawing, a third of the drawing time of the machine page.
    height_in = 2.3 * rows
    fig = Figure(figsize=(10, height_in), dpi=90)
    fig.subplots_adjust(
        left=0.08, right=0.955, top=1 - 0.3 / height_in, bottom=0.75 / height_in, hspace=0.12
    )
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    days = LocalDays(span_s)
    at, labels = days.ticks(span_s)
    for ax in axes:
        ax.xaxis.set_major_locator(FixedLocator(at.tolist()))
    axes[-1].xaxis.set_major_formatter(FixedFormatter(labels))
    axes[-1].set_xlim(*days(np.asarray(span_s)))
    return fig, [_Panel(ax, days) for ax in axes]


def _svg(fig: Any) -> str:
    out = io.StringIO()
    fig.savefig(out, format="svg")
    return out.getvalue()


def _axis_panel(panel: _Panel, axis: str, lines: Mapping[str, Series]) -> None:
    """One further axis's compensation: predicted, applied, and what its CNC macro holds."""
    panel.line(lines["predicted_um"], "predicted")
    panel.line(lines["applied_um"], "applied")
    panel.line(lines["cnc_um"], "CNC holds", linestyle="--")
    panel.ax.set_ylabel(f"{axis} compensation (µm)")


def _probes(panel: _Panel, data: MachineView) -> None:
    """Each probe a marker; more probes than the plot has columns (a month of probes
    every 2 min: the column's extremes, thousands) as lines through them, which read
    the same at that density and cost the drawing and the browser a fraction."""
    t = data.probe_t_s
    if len(t) > COLUMNS:
        panel.line((t, data.probe_error_um), "probe measured")
        panel.line((t, data.probe_residual_um), "residual", linestyle=":")
    elif len(t):
        dates = panel.days(t)
        panel.ax.plot(dates, data.probe_error_um, "o", markersize=4, label="probe measured")
        panel.ax.plot(dates, data.probe_residual_um, "x", markersize=5, label="residual")


def machine_svg(data: MachineView, title: str) -> str:
    """The machine page's panels: temperatures, speed, compensation (a multi-axis
    machine's first axis), one per further axis, probes.

    Text is written as SVG text (the browser sets it) and a line's vertices closer
    than half a pixel to the line through their neighbours are dropped: a day's page
    is then about 420 kB instead of 650 kB, which the browser also decodes faster."""
    import matplotlib

    with matplotlib.rc_context(SVG_STYLE):  # type: ignore[arg-type]
        return _machine_svg(data, title)


def _machine_svg(data: MachineView, title: str) -> str:
    further = list(data.axis_lines)[1:]
    fig, panels = _figure(4 + len(further), _extent_of(data))
    temps, speed, comp, *axis_panels, probe = panels
    for sensor, series in sorted(data.temperatures_C.items()):
        temps.line(series, sensor)
    temps.ax.set_ylabel("temperature (°C)")
    lines = data.lines
    speed.line(lines["speed_rpm"], "speed")
    speed.ax.set_ylabel("speed (r/min)")
    comp.line(lines["predicted_um"], "predicted")
    if "interval_low_um" in lines and np.isfinite(lines["interval_high_um"][1]).any():
        comp.line(lines["interval_low_um"], "90 % interval", color="grey", linestyle="-.")
        comp.line(lines["interval_high_um"], "_nolegend_", color="grey", linestyle="-.")
    comp.line(lines["applied_um"], "applied")
    comp.line(lines["cnc_um"], "CNC holds", linestyle="--")
    comp.line(lines["correction_um"], "online correction", linestyle=":")
    comp.ax.set_ylabel(f"{next(iter(data.axis_lines), 'Z')} compensation (µm)")
    for panel, axis in zip(axis_panels, further, strict=True):
        _axis_panel(panel, axis, data.axis_lines[axis])
    _probes(probe, data)
    probe.ax.axhline(0.0, color="grey", linewidth=0.5)
    probe.ax.set_ylabel("probe error (µm)")
    probe.ax.set_xlabel("local time")
    for ax in (p.ax for p in panels):
        ax.grid(True, linewidth=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", fontsize=7, ncols=6)
    temps.ax.set_title(title, fontsize=10)
    return _svg(fig)


def proposal_svg(
    probe_t_s: np.ndarray, residual_um: np.ndarray, before_rmse_um: float, after_rmse_um: float
) -> str:
    """A proposal's effect: the logged probe residuals, and its held-out RMSE before/after."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 2.6), dpi=90, layout="constrained")
    resid, bars = fig.subplots(1, 2, width_ratios=[3, 1])
    if len(probe_t_s):
        resid.plot(_dates(probe_t_s), residual_um, "o", markersize=4)
    resid.axhline(0.0, color="grey", linewidth=0.5)
    resid.set_ylabel("logged probe residual (µm)")
    resid.set_xlabel("local time")
    resid.grid(True, linewidth=0.3)
    bars.bar(["before", "after"], [before_rmse_um, after_rmse_um], color=["#b55", "#5a5"])
    bars.set_ylabel("held-out RMSE (µm)")
    return _svg(fig)


def read_machine_view(
    spec: SourceSpec,
    machine: str,
    window_s: float,
    cnc_um_per_unit: float,
    axes: Mapping[str, float] | None = None,
) -> MachineView:
    """Worker entry: the last ``window_s`` of ``machine`` as the page draws it (its
    events for the page, its lines for :func:`draw_machine`). ``axes``: a multi-axis
    machine's, each with its CNC value's µm per unit."""
    now = time.time()
    return machine_view(spec, machine, now - window_s, now, cnc_um_per_unit, COLUMNS, axes=axes)


def draw_machine(data: MachineView, machine: str) -> str:
    """Worker entry: the page's plot of a view read by :func:`read_machine_view`."""
    start, stop = data.window_s or _extent_of(data)
    return machine_svg(data, f"{machine}: last {(stop - start) / 3600:g} h ({data.cycles} cycles)")


def render_proposal(
    spec: SourceSpec,
    machine: str,
    window_s: float,
    before_um: float,
    after_um: float,
    axes: Sequence[str] = (),
) -> str:
    """Worker entry: a proposal's plot (residuals against the first of ``axes``, which
    the probe measures, or the single axis)."""
    now = time.time()
    probe_t_s, _, residual_um = read_probes(spec, machine, now - window_s, now, axes)
    return proposal_svg(probe_t_s, residual_um, before_um, after_um)


def _import_plotting() -> None:
    """Worker entry: import what drawing needs (the worker keeps the modules)."""
    import matplotlib.figure  # noqa: F401


@dataclass
class _Cached:
    made_s: float
    svg: Any


class PlotRenderer:
    """One worker process for every plot; results cached for ``cache_s`` per request."""

    def __init__(self, cache_s: float = 15.0, max_entries: int = 64) -> None:
        self.cache_s = cache_s
        self.max_entries = max_entries
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._cache: dict[tuple[Any, ...], _Cached] = {}
        self._pending: dict[tuple[Any, ...], asyncio.Future[Any]] = {}

    async def render(
        self, key: tuple[Any, ...], function: Any, *args: Any, max_age_s: float | None = None
    ) -> Any:
        """``function(*args)`` in the worker: cached for ``max_age_s`` (default
        ``cache_s``), one computation shared by concurrent requests."""
        hit = self._cache.get(key)
        age_s = self.cache_s if max_age_s is None else max_age_s
        if hit is not None and time.monotonic() - hit.made_s < age_s:
            return hit.svg
        pending = self._pending.get(key)
        if pending is None:
            loop = asyncio.get_running_loop()
            pending = asyncio.ensure_future(loop.run_in_executor(self._executor(), function, *args))
            self._pending[key] = pending
            pending.add_done_callback(lambda _: self._pending.pop(key, None))
        svg = await asyncio.shield(pending)
        if len(self._cache) >= self.max_entries:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = _Cached(time.monotonic(), svg)
        return svg

    def clear(self) -> None:
        """Forget every drawn result (the next request reads and draws afresh)."""
        self._cache.clear()

    def warm(self) -> None:
        """Start the worker and its imports now (a person just logged in and a plot is
        likely next), so the first plot does not also wait for a new interpreter to
        import numpy and matplotlib. Nothing is awaited; a second call does nothing."""
        if self._pool is None:
            self._executor().submit(_import_plotting)

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            context = multiprocessing.get_context("spawn")  # no fork of the running loop
            self._pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=context)
        return self._pool

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
