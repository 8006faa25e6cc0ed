"""Server-side plots as SVG (matplotlib), drawn in a worker process off the event loop.

The machine page draws :func:`gateway.web.series.machine_view`: each line already cut
to a min/max envelope per pixel column of the window (24 h of 1 Hz data, 86 400
points a series, becomes at most two points per column, every spike still visible).
Rendering runs in one spawned worker process (:class:`PlotRenderer`), so neither
the drawing nor the reading of the store holds the gateway's interpreter; the
newest SVG of each request is kept for ``cache_s``.
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

from gateway.web.series import COLUMNS, MachineView, SourceSpec, machine_view, read_probes


def _dates(t: np.ndarray) -> list[datetime]:
    return [datetime.fromtimestamp(float(x)) for x in t]


def _line(ax: Any, series: tuple[np.ndarray, np.ndarray], label: str, **style: Any) -> None:
    t, y = series
    if len(t):
        ax.plot(_dates(t), y, label=label, linewidth=0.9, **style)


def _figure(rows: int) -> tuple[Any, Sequence[Any]]:
    from matplotlib.figure import Figure

    # Fixed margins: a constrained layout measures every label once more before
    # drawing, a third of the drawing time of the machine page.
    height_in = 2.3 * rows
    fig = Figure(figsize=(10, height_in), dpi=90)
    fig.subplots_adjust(
        left=0.08, right=0.955, top=1 - 0.3 / height_in, bottom=0.55 / height_in, hspace=0.12
    )
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    return fig, list(axes)


def _svg(fig: Any) -> str:
    out = io.StringIO()
    fig.savefig(out, format="svg")
    return out.getvalue()


def _axis_panel(ax: Any, axis: str, lines: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """One further axis's compensation: predicted, applied, and what its CNC macro holds."""
    _line(ax, lines["predicted_um"], "predicted")
    _line(ax, lines["applied_um"], "applied")
    _line(ax, lines["cnc_um"], "CNC holds", linestyle="--")
    ax.set_ylabel(f"{axis} compensation (µm)")


def machine_svg(data: MachineView, title: str) -> str:
    """The machine page's panels: temperatures, speed, compensation (a multi-axis
    machine's first axis), one per further axis, probes."""
    further = list(data.axis_lines)[1:]
    fig, panels = _figure(4 + len(further))
    temps, speed, comp, *axis_panels, probe = panels
    for sensor, series in sorted(data.temperatures_C.items()):
        _line(temps, series, sensor)
    temps.set_ylabel("temperature (°C)")
    lines = data.lines
    _line(speed, lines["speed_rpm"], "speed")
    speed.set_ylabel("speed (r/min)")
    _line(comp, lines["predicted_um"], "predicted")
    if "interval_low_um" in lines and np.isfinite(lines["interval_high_um"][1]).any():
        _line(comp, lines["interval_low_um"], "90 % interval", color="grey", linestyle="-.")
        _line(comp, lines["interval_high_um"], "_nolegend_", color="grey", linestyle="-.")
    _line(comp, lines["applied_um"], "applied")
    _line(comp, lines["cnc_um"], "CNC holds", linestyle="--")
    _line(comp, lines["correction_um"], "online correction", linestyle=":")
    comp.set_ylabel(f"{next(iter(data.axis_lines), 'Z')} compensation (µm)")
    for ax, axis in zip(axis_panels, further, strict=True):
        _axis_panel(ax, axis, data.axis_lines[axis])
    if len(data.probe_t_s):
        dates = _dates(data.probe_t_s)
        probe.plot(dates, data.probe_error_um, "o", markersize=4, label="probe measured")
        probe.plot(dates, data.probe_residual_um, "x", markersize=5, label="residual")
    probe.axhline(0.0, color="grey", linewidth=0.5)
    probe.set_ylabel("probe error (µm)")
    probe.set_xlabel("local time")
    for ax in panels:
        ax.grid(True, linewidth=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", fontsize=7, ncols=6)
    temps.set_title(title, fontsize=10)
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


def render_machine(
    spec: SourceSpec,
    machine: str,
    window_s: float,
    cnc_um_per_unit: float,
    axes: Mapping[str, float] | None = None,
) -> tuple[str, list[tuple[float, str, str]]]:
    """Worker entry: read the window once, draw it and list its events (in the plot
    process); the page and its plot share the result through the cache. ``axes``: a
    multi-axis machine's, each with its CNC value's µm per unit."""
    now = time.time()
    data = machine_view(spec, machine, now - window_s, now, cnc_um_per_unit, COLUMNS, axes=axes)
    hours = window_s / 3600
    return machine_svg(data, f"{machine}: last {hours:g} h ({data.cycles} cycles)"), data.events


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
