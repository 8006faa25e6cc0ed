"""HTML report of a residual analysis, for the machine-tool engineer who will not read the JSON.

``python -m gateway analyze DATA.csv --report DIR`` calls :func:`write_report`,
which writes ``DIR/index.html`` and the PNG plots it shows:

* ``residual_runs.png``: held-out residual over time of every run, before and
  after the added effects;
* ``measured_vs_predicted.png``: measured error and held-out predictions;
* ``step<N>_signal.png``: for each step that added an effect, the residual
  before that step against the effect's signal;
* ``candidates.png``: held-out RMSE of every candidate of the first step.

Plots are drawn on :class:`matplotlib.figure.Figure` with the Agg canvas, never
through pyplot: no global figure registry to leak into, no GUI backend needed on
the gateway, and the figure is freed as soon as it goes out of scope.
The page itself is :func:`models.analysis.render.html_report` (a Jinja2 template with
autoescape on), so it shows exactly the figures of the terminal table and the
JSON; every string from the data is escaped there, and here has its ``$``
escaped (matplotlib mathtext), so a sensor or run name cannot break the page.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from models.analysis.format import effect_name, um_text
from models.analysis.render import after_label, before_label, html_report
from models.analysis.result import AnalysisResult, StepResult, run_groups

DPI = 100
MAX_SCATTER_POINTS = 20_000
MAX_RUNS_IN_ONE_COLUMN = 12

BEFORE_COLOUR = "tab:orange"
AFTER_COLOUR = "tab:blue"
MEASURED_COLOUR = "black"
BELIEVED_COLOUR = "tab:green"
OTHER_COLOUR = "0.65"

CAPTION_RESIDUAL_RUNS = (
    "Held-out residual (measured − predicted) of each run over time, each run predicted by a "
    "model fitted without it. Before: a systematic pattern — a residual that keeps growing "
    "after the speed changes, a slow trend through the run, an offset between runs — is an "
    "effect the model lacks. After: the residual should stay flat around zero within the "
    "measurement noise, in every run and not only on average."
)
CAPTION_MEASURED = (
    "Measured thermal error and the held-out predictions of each run. Look for the 'after' "
    "curve following the measured one through heating and cooling, including the turning "
    "points. Runs where both predictions miss by a similar amount point to conditions that "
    "the other runs did not cover."
)
CAPTION_SIGNAL = (
    "Residual before this step against the signal of the effect it added. Before: a slope "
    "or curve in the cloud means the residual depends on this signal — the effect was "
    "missing. After: the cloud should be flat around zero; a remaining slope means the "
    "effect is only partly captured, a remaining spread is due to something else."
)
CAPTION_CANDIDATES = (
    "Held-out RMSE of every candidate tried at the first step; the dashed line is the RMSE "
    "before the step. Coloured bars passed every rule (believed), grey bars did not: a grey "
    "bar left of the line lowered the average error but failed a rule (e.g. too few folds "
    "improved, not significant) — the reason column of the table above says which."
)


@dataclass(frozen=True)
class _Plot:
    """A written PNG and the caption that tells the reader what to look for."""

    file: str
    title: str
    caption: str


def write_report(result: AnalysisResult, folder: str | Path) -> Path:
    """Write index.html and PNG plots into folder (created if missing); return the index.html path.

    The plots are written first so the page only references files that exist.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    plots = _write_plots(result, out)
    index = out / "index.html"
    index.write_text(html_report(result, plots), encoding="utf-8")
    return index


# --------------------------------------------------------------------------- text helpers


def _plain(text: str) -> str:
    """Stop matplotlib reading ``$…$`` in a data string as mathtext."""
    return text.replace("$", r"\$")


# --------------------------------------------------------------------------- runs


def _grid_shape(n_runs: int) -> tuple[int, int]:
    """One column up to 12 runs (easy to compare); a near-square grid beyond."""
    if n_runs <= MAX_RUNS_IN_ONE_COLUMN:
        return max(n_runs, 1), 1
    ncols = math.ceil(math.sqrt(n_runs))
    return math.ceil(n_runs / ncols), ncols


def _new_figure(width_in: float, height_in: float) -> Figure:
    """A pyplot-free figure on the Agg canvas (no global state, nothing to close)."""
    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _run_axes(n_runs: int) -> tuple[Figure, list[Axes]]:
    """One subplot per run with a shared y axis, so runs compare at a glance."""
    nrows, ncols = _grid_shape(n_runs)
    width = 10.0 if ncols == 1 else 3.2 * ncols
    fig = _new_figure(width, 1.2 + 1.8 * nrows)
    axes = list(fig.subplots(nrows, ncols, sharey=True, squeeze=False).ravel())
    for ax in axes[n_runs:]:
        ax.set_visible(False)
    return fig, axes[:n_runs]


def _save(fig: Figure, path: Path) -> None:
    fig.savefig(path, dpi=DPI)
    fig.clear()


# --------------------------------------------------------------------------- plots


def _write_plots(result: AnalysisResult, out: Path) -> list[_Plot]:
    """Draw every plot the report shows, in the order it shows them."""
    groups = run_groups(result.run, result.time_s)
    plots = [
        _residual_runs_plot(result, groups, out),
        _measured_vs_predicted_plot(result, groups, out),
    ]
    for step in result.steps:
        if step.effect != "none" and step.signal is not None:
            plots.append(_step_signal_plot(result, step, step.signal, out))
    if result.steps and result.steps[0].candidates:
        plots.append(_candidates_plot(result.steps[0], out))
    return plots


def _residual_runs_plot(
    result: AnalysisResult, groups: Sequence[tuple[str, np.ndarray]], out: Path
) -> _Plot:
    """Residual over time per run: lags and trends show as shapes, not as one number."""
    before = result.measured_um - result.predicted_before_um
    after = result.measured_um - result.predicted_after_um
    fig, axes = _run_axes(len(groups))
    for ax, (name, rows) in zip(axes, groups, strict=True):
        hours = result.time_s[rows] / 3600.0
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.plot(
            hours, before[rows], color=BEFORE_COLOUR, lw=1.0, label=_plain(before_label(result))
        )
        ax.plot(hours, after[rows], color=AFTER_COLOUR, lw=1.0, label=_plain(after_label(result)))
        ax.set_title(_plain(name), fontsize=9, loc="left")
        ax.grid(alpha=0.3)
    _finish_run_figure(fig, axes, "residual measured − predicted (µm)")
    _save(fig, out / "residual_runs.png")
    return _Plot("residual_runs.png", "Residual over time, per run", CAPTION_RESIDUAL_RUNS)


def _measured_vs_predicted_plot(
    result: AnalysisResult, groups: Sequence[tuple[str, np.ndarray]], out: Path
) -> _Plot:
    """Measured error and both predictions, to judge the fit against the error's own size."""
    fig, axes = _run_axes(len(groups))
    for ax, (name, rows) in zip(axes, groups, strict=True):
        hours = result.time_s[rows] / 3600.0
        ax.plot(hours, result.measured_um[rows], color=MEASURED_COLOUR, lw=1.2, label="measured")
        ax.plot(
            hours,
            result.predicted_before_um[rows],
            color=BEFORE_COLOUR,
            lw=1.0,
            label=_plain(before_label(result)),
        )
        ax.plot(
            hours,
            result.predicted_after_um[rows],
            color=AFTER_COLOUR,
            lw=1.0,
            ls="--",
            label=_plain(after_label(result)),
        )
        ax.set_title(_plain(name), fontsize=9, loc="left")
        ax.grid(alpha=0.3)
    _finish_run_figure(fig, axes, _plain(f"measured and predicted {result.target} (µm)"))
    _save(fig, out / "measured_vs_predicted.png")
    return _Plot(
        "measured_vs_predicted.png", "Measured error and held-out predictions", CAPTION_MEASURED
    )


def _finish_run_figure(fig: Figure, axes: Sequence[Axes], ylabel: str) -> None:
    """Common axis labels and one legend above all subplots."""
    fig.supxlabel("time (h)")
    fig.supylabel(ylabel)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncols=len(labels), fontsize=9)


def _subsample(n: int) -> np.ndarray:
    """At most MAX_SCATTER_POINTS row indices, reproducibly, so big files plot fast."""
    if n <= MAX_SCATTER_POINTS:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, MAX_SCATTER_POINTS, replace=False))


def _step_signal_plot(
    result: AnalysisResult, step: StepResult, signal: np.ndarray, out: Path
) -> _Plot:
    """Residual against the added effect's signal: the evidence the effect was missing."""
    signal = np.asarray(signal, dtype=float)
    before = result.measured_um - step.predicted_before_um
    after = result.measured_um - step.predicted_after_um
    rows = _subsample(signal.size)
    name = effect_name(step.effect, step.params)

    fig = _new_figure(8.0, 5.0)
    ax = fig.subplots()
    ax.axhline(0.0, color="0.6", lw=0.6)
    style: dict[str, Any] = {"s": 4, "alpha": 0.35, "linewidths": 0}
    ax.scatter(signal[rows], before[rows], color=BEFORE_COLOUR, label="before this step", **style)
    ax.scatter(
        signal[rows], after[rows], color=AFTER_COLOUR, label=_plain(f"after: + {name}"), **style
    )
    ax.set_xlabel(_plain(step.signal_label or "signal"))
    ax.set_ylabel("residual measured − predicted (µm)")
    ax.set_title(_plain(f"Step {step.number}: residual against the signal of {name}"), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(markerscale=3, fontsize=9)
    file = f"step{step.number}_signal.png"
    _save(fig, out / file)
    return _Plot(file, f"Step {step.number}: residual against {name}", CAPTION_SIGNAL)


def _candidates_plot(step: StepResult, out: Path) -> _Plot:
    """How far each candidate got, so the engineer sees the choice was not close (or was)."""
    candidates = sorted(step.candidates, key=lambda c: c.rmse_um)
    y = np.arange(len(candidates))
    fig = _new_figure(8.0, 1.5 + 0.32 * len(candidates))
    ax = fig.subplots()
    ax.barh(
        y,
        [c.rmse_um for c in candidates],
        color=[BELIEVED_COLOUR if c.believed else OTHER_COLOUR for c in candidates],
    )
    ax.set_yticks(y, labels=[_plain(effect_name(c.effect, c.params)) for c in candidates])
    ax.tick_params(axis="y", labelsize=8)
    ax.invert_yaxis()
    ax.axvline(step.before.rmse_um, color="black", ls="--", lw=1.0)
    ax.set_xlabel("held-out RMSE (µm)")
    ax.set_title(f"Step {step.number}: candidates", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    fig.legend(
        handles=[
            Patch(color=BELIEVED_COLOUR, label="believed (passed every rule)"),
            Patch(color=OTHER_COLOUR, label="not believed"),
            Line2D(
                [], [], color="black", ls="--", label=f"before: {um_text(step.before.rmse_um)} µm"
            ),
        ],
        fontsize=8,
        ncols=3,
        loc="outside lower center",
    )
    _save(fig, out / "candidates.png")
    return _Plot("candidates.png", "Candidates of the first step", CAPTION_CANDIDATES)
