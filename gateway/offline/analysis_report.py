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
Every string that comes from the data is escaped (HTML) or has its ``$``
escaped (matplotlib mathtext), so a sensor or run name cannot break the page.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from models.analysis_result import AnalysisResult, CandidateResult, StepResult
from models.metrics import Accuracy

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

CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 72em; color: #222;
       padding: 0 1em; line-height: 1.4; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.6em; }
.summary { font-size: 1.15em; background: #f3f6fa; padding: 0.6em 0.8em;
           border-left: 4px solid #1f77b4; }
table { border-collapse: collapse; margin: 0.6em 0; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left;
         vertical-align: top; }
th { background: #f0f0f0; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.chosen td { background: #e3f4e1; font-weight: bold; }
ul.kv { margin: 0; padding-left: 1.2em; }
figure { margin: 1.2em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { max-width: 60em; color: #444; }
"""


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
    index.write_text(_html_page(result, plots), encoding="utf-8")
    return index


# --------------------------------------------------------------------------- text helpers


def _esc(value: Any) -> str:
    """HTML-escape anything that came from the data."""
    return html.escape(str(value), quote=True)


def _plain(text: str) -> str:
    """Stop matplotlib reading ``$…$`` in a data string as mathtext."""
    return text.replace("$", r"\$")


def _minus(text: str) -> str:
    """Typographic minus, as an engineer would write it."""
    return text.replace("-", "−")


def _um(value: float) -> str:
    """A length in µm, to the 0.01 µm the measurements support."""
    return f"{value:.2f}"


def _p_value(value: float) -> str:
    """Three significant digits (e.g. ``1.2e-05``); a dash when there is no test."""
    return f"{value:.3g}" if math.isfinite(value) else "—"


def _value(value: Any) -> str:
    """A parameter or dictionary value in short readable form (1800.0 → 1800)."""
    if isinstance(value, bool | str):
        return str(value)
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return f"{float(value):g}"
    if isinstance(value, Mapping):
        return _params(value)
    if isinstance(value, list | tuple):
        return ", ".join(_value(v) for v in value)
    if value is None:
        return "—"
    return json.dumps(value, default=str)


def _params(params: Mapping[str, Any]) -> str:
    """``k = v`` pairs, the way the summary and tables name a parameter choice."""
    return ", ".join(f"{key} = {_value(val)}" for key, val in params.items())


def _effect_name(effect: str, params: Mapping[str, Any]) -> str:
    """Effect with its parameters, e.g. ``thermal_lag (tau_s = 1800)``."""
    return f"{effect} ({_params(params)})" if params else effect


def _added_steps(result: AnalysisResult) -> list[StepResult]:
    return [step for step in result.steps if step.effect != "none"]


def _before_label(result: AnalysisResult) -> str:
    return f"before: {result.model}"


def _after_label(result: AnalysisResult) -> str:
    effects = result.effects
    return "after: + " + " + ".join(effects) if effects else "after: nothing added"


def _summary(result: AnalysisResult) -> str:
    """The one sentence the reader needs if they read nothing else."""
    before, after = result.before.rmse_um, result.after.rmse_um
    added = _added_steps(result)
    if not added:
        return (
            f"No effect is missing: no candidate passed the rules ({result.effect}). "
            f"Held-out RMSE stays at {_um(before)} µm."
        )
    change = f" ({_minus(f'{100.0 * (after / before - 1.0):+.0f}')} %)" if before > 0 else ""
    names = ", then ".join(_effect_name(step.effect, step.params) for step in added)
    return f"Held-out RMSE {_um(before)} µm → {_um(after)} µm{change} by adding {names}."


# --------------------------------------------------------------------------- runs


def _run_groups(run: np.ndarray, time_s: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Row indices of each run, runs in order of first appearance, rows in time order.

    The order of the file is the order the engineer knows the runs by, so it is
    kept rather than sorting the names.
    """
    names = np.asarray(run).astype(str)
    unique, first, inverse = np.unique(names, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    groups = []
    for k in np.argsort(first, kind="stable"):
        rows = np.flatnonzero(inverse == k)
        rows = rows[np.argsort(time_s[rows], kind="stable")]
        groups.append((str(unique[k]), rows))
    return groups


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
    groups = _run_groups(result.run, result.time_s)
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
            hours, before[rows], color=BEFORE_COLOUR, lw=1.0, label=_plain(_before_label(result))
        )
        ax.plot(hours, after[rows], color=AFTER_COLOUR, lw=1.0, label=_plain(_after_label(result)))
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
            label=_plain(_before_label(result)),
        )
        ax.plot(
            hours,
            result.predicted_after_um[rows],
            color=AFTER_COLOUR,
            lw=1.0,
            ls="--",
            label=_plain(_after_label(result)),
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
    name = _effect_name(step.effect, step.params)

    fig = _new_figure(8.0, 5.0)
    ax = fig.subplots()
    ax.axhline(0.0, color="0.6", lw=0.6)
    style = {"s": 4, "alpha": 0.35, "linewidths": 0}
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
    ax.set_yticks(y, labels=[_plain(_effect_name(c.effect, c.params)) for c in candidates])
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
            Line2D([], [], color="black", ls="--", label=f"before: {_um(step.before.rmse_um)} µm"),
        ],
        fontsize=8,
        ncols=3,
        loc="outside lower center",
    )
    _save(fig, out / "candidates.png")
    return _Plot("candidates.png", "Candidates of the first step", CAPTION_CANDIDATES)


# --------------------------------------------------------------------------- HTML


def _html_page(result: AnalysisResult, plots: Sequence[_Plot]) -> str:
    """The whole page: summary first, evidence after, plots last."""
    title = f"Thermal-error analysis: {result.model} → {result.target}"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{_esc(title)}</title>",
        f"<style>{CSS}</style></head><body>",
        f"<h1>{_esc(title)}</h1>",
        f'<p class="summary">{_esc(_summary(result))}</p>',
        _accuracy_section(result),
        _facts_section(result),
        *(_step_section(step) for step in result.steps),
        _plots_section(plots),
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"


def _accuracy_row(label: str, acc: Accuracy) -> str:
    cells = [_um(acc.rmse_um), _um(acc.sigma_um), _um(acc.max_abs_um), str(acc.n_samples)]
    tds = "".join(f'<td class="num">{c}</td>' for c in cells)
    return f"<tr><th>{_esc(label)}</th>{tds}</tr>"


def _accuracy_section(result: AnalysisResult) -> str:
    """Before/after held-out figures: the numbers the decision rests on."""
    return "\n".join(
        [
            "<h2>Held-out accuracy</h2>",
            "<table>",
            "<tr><th></th><th>RMSE (µm)</th><th>σ (µm)</th><th>max |e| (µm)</th>"
            "<th>samples</th></tr>",
            _accuracy_row(_before_label(result), result.before),
            _accuracy_row(_after_label(result), result.after),
            "</table>",
            "<p>e = measured − predicted, each run predicted by a model fitted without it. "
            "σ ignores a constant offset, RMSE does not.</p>",
        ]
    )


def _kv_list(data: Mapping[str, Any]) -> str:
    """A dictionary as ``key: value`` lines."""
    if not data:
        return "—"
    items = "".join(f"<li>{_esc(key)}: {_esc(_value(val))}</li>" for key, val in data.items())
    return f'<ul class="kv">{items}</ul>'


def _runs_text(result: AnalysisResult) -> str:
    groups = _run_groups(result.run, result.time_s)
    listed = ", ".join(f"{name} ({rows.size} rows)" for name, rows in groups)
    return f"{len(groups)}: {listed}"


def _facts_section(result: AnalysisResult) -> str:
    """How the figures were obtained, so the result can be reproduced and trusted."""
    rows: list[tuple[str, str]] = [
        ("Model", _esc(result.model)),
        ("Target", _esc(result.target)),
        ("Sensors", _esc(", ".join(result.sensors) or "—")),
        ("Runs", _esc(_runs_text(result))),
        ("Validation", _esc(result.validation)),
        ("Reference", _kv_list(result.reference)),
        ("Rules", _kv_list(result.rules)),
        ("Source file", _esc(result.source or "—")),
        ("Data fingerprint", f"<code>{_esc(result.data_fingerprint or '—')}</code>"),
    ]
    if result.skipped_rows:
        rows.append(("Skipped rows", _esc(result.skipped_rows)))
    if result.stored_model:
        rows.append(("Stored model", _kv_list(result.stored_model)))
    body = "".join(f"<tr><th>{_esc(name)}</th><td>{value}</td></tr>" for name, value in rows)
    return f"<h2>Validation and data</h2>\n<table>{body}</table>"


def _chosen_index(step: StepResult) -> int | None:
    """The candidate that was added: same effect and parameters, else same effect."""
    if step.effect == "none":
        return None
    for i, cand in enumerate(step.candidates):
        if cand.effect == step.effect and cand.params == step.params:
            return i
    for i, cand in enumerate(step.candidates):
        if cand.effect == step.effect:
            return i
    return None


def _candidate_row(cand: CandidateResult, chosen: bool) -> str:
    cells = [
        ("", _esc(cand.effect)),
        ("", _esc(_params(cand.params) or "—")),
        ("", _esc(cand.label)),
        ("num", _um(cand.rmse_um)),
        ("num", _minus(f"{cand.gain_pct:.1f}")),
        ("num", f"{cand.folds_improved}/{cand.folds}"),
        ("num", _esc(_p_value(cand.p_value))),
        ("", "yes" if cand.believed else "no"),
        ("", _esc(cand.reason)),
    ]
    tds = "".join(
        f'<td class="{cls}">{text}</td>' if cls else f"<td>{text}</td>" for cls, text in cells
    )
    return f'<tr class="chosen">{tds}</tr>' if chosen else f"<tr>{tds}</tr>"


CANDIDATE_HEADER = (
    "<tr><th>effect</th><th>params</th><th>label</th><th>held-out RMSE (µm)</th>"
    "<th>gain (%)</th><th>folds improved</th><th>p-value</th><th>believed</th>"
    "<th>reason</th></tr>"
)


def _step_section(step: StepResult) -> str:
    """One round of the search: what was tried, what was added, or why it stopped."""
    if step.effect == "none":
        heading = f"Step {step.number}: nothing added"
        text = (
            f"No candidate passed every rule, so the analysis stopped here; the held-out RMSE "
            f"stays at {_um(step.before.rmse_um)} µm. The reason column says which rule each "
            f"candidate failed."
        )
    else:
        name = _effect_name(step.effect, step.params)
        heading = f"Step {step.number}: added {name}"
        text = (
            f"Held-out RMSE {_um(step.before.rmse_um)} µm → {_um(step.after.rmse_um)} µm. "
            f"The chosen candidate is highlighted."
        )
    chosen = _chosen_index(step)
    if step.candidates:
        rows = "".join(_candidate_row(c, i == chosen) for i, c in enumerate(step.candidates))
        table = f"<table>{CANDIDATE_HEADER}{rows}</table>"
    else:
        table = "<p>No candidates were tried.</p>"
    return f"<h2>{_esc(heading)}</h2>\n<p>{_esc(text)}</p>\n{table}"


def _plots_section(plots: Sequence[_Plot]) -> str:
    figures = "\n".join(
        f'<figure><img src="{_esc(p.file)}" alt="{_esc(p.title)}">'
        f"<figcaption><b>{_esc(p.title)}.</b> {_esc(p.caption)}</figcaption></figure>"
        for p in plots
    )
    return f"<h2>Plots</h2>\n{figures}"
