"""Formatting an analysis result: one set of cells, laid out as text or as HTML.

Every figure the terminal and the report show goes through the formatters here
(:func:`um_text`, :func:`change_text`, :func:`p_text`, :func:`params_text`),
and every table is built once as rows of cells (:func:`candidate_rows`,
:func:`accuracy_rows`, :func:`run_rows`) that :func:`text_report` pads into
columns and the Jinja2 template (``templates/analysis_report.html.j2``,
autoescaped) puts into ``<td>``: the two cannot show different numbers.

Conventions for people: µm to 0.01, percentages to 0.1, a change of the RMSE
signed (−25.5 % is less error), time constants in minutes, p-values to three
significant digits and never 0 (below ``P_FLOOR`` they read "< 1e-16").
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from models.analysis_result import P_FLOOR

if TYPE_CHECKING:
    from models.analysis_result import AnalysisResult, CandidateResult, StepResult

TEMPLATE = "analysis_report.html.j2"

CANDIDATE_HEADER = (
    "",
    "effect",
    "parameters",
    "held-out RMSE (µm)",
    "RMSE change (%)",
    "shape change (%)",
    "folds better",
    "p-value",
    "believed",
    "reason",
)
NUMERIC_CANDIDATE_COLUMNS = frozenset({3, 4, 5, 6, 7})
ACCURACY_HEADER = ("", "RMSE (µm)", "σ (µm)", "max |e| (µm)", "samples")
RUN_HEADER = ("run", "samples", "RMSE before (µm)", "RMSE after (µm)", "share of error after (%)")


# --------------------------------------------------------------------------- formatters


def minus(text: str) -> str:
    """Typographic minus, as an engineer would write it."""
    return text.replace("-", "−")


def um_text(value: float) -> str:
    """A length in µm, to the 0.01 µm the measurements support."""
    return f"{value:.2f}" if math.isfinite(value) else "—"


def pct_text(value: float) -> str:
    """A share or gain in %, to 0.1."""
    return minus(f"{value:.1f}") if math.isfinite(value) else "—"


def change_text(gain_pct: float) -> str:
    """A gain shown as the signed change of the error: gain 25.5 → "−25.5"."""
    return minus(f"{-gain_pct:+.1f}") if math.isfinite(gain_pct) else "—"


def p_text(value: float) -> str:
    """Three significant digits (``1.23e-05``), "< 1e-16" below the floor, a dash if untested."""
    if not math.isfinite(value):
        return "—"
    if value < P_FLOOR:
        return f"< {P_FLOOR:.0e}"
    return f"{value:.3g}"


def minutes_text(tau_s: float) -> str:
    """A time constant for people: 1800 s → "30 min"."""
    return f"{float(tau_s) / 60.0:g} min"


def value_text(value: Any) -> str:
    """A parameter or dictionary value in short readable form (1800.0 → 1800)."""
    if isinstance(value, bool | str):
        return str(value)
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return f"{float(value):g}"
    if isinstance(value, Mapping):
        return ", ".join(f"{key} = {value_text(val)}" for key, val in value.items())
    if isinstance(value, list | tuple):
        return ", ".join(value_text(v) for v in value)
    if value is None:
        return "—"
    return json.dumps(value, default=str)


def params_text(params: Mapping[str, Any]) -> str:
    """``k = v`` pairs, a time constant as ``τ = 30 min``; empty for no parameters."""
    parts = []
    for key, val in params.items():
        if key == "tau_s":
            parts.append(f"τ = {minutes_text(val)}")
        else:
            parts.append(f"{key} = {value_text(val)}")
    return ", ".join(parts)


def effect_name(effect: str, params: Mapping[str, Any]) -> str:
    """Effect with its parameters, e.g. ``thermal_lag (τ = 30 min)``."""
    return f"{effect} ({params_text(params)})" if params else effect


def tolerance_text(result: AnalysisResult) -> str:
    verdict = "met" if result.within_tolerance else "not met"
    return f"tolerance {um_text(result.tolerance_um)} µm: {verdict}"


def headline(result: AnalysisResult) -> str:
    """The one sentence the reader needs if they read nothing else."""
    before, after = result.before.rmse_um, result.after.rmse_um
    added = result.added_steps
    if not added:
        return (
            f"No effect is missing: no candidate passed the rules ({result.effect}). "
            f"Held-out RMSE stays at {um_text(before)} µm; {tolerance_text(result)}."
        )
    names = ", then ".join(effect_name(step.effect, step.params) for step in added)
    return (
        f"Held-out RMSE {um_text(before)} µm → {um_text(after)} µm "
        f"({change_text(result.rmse_gain_pct)} %) by adding {names}; {tolerance_text(result)}."
    )


def step_text(step: StepResult) -> str:
    """What one round did, in one sentence."""
    if step.effect == "none":
        return (
            f"No candidate passed every rule, so the analysis stopped here; the held-out RMSE "
            f"stays at {um_text(step.before.rmse_um)} µm. The reason column says which rule "
            "each candidate failed."
        )
    return (
        f"Added {effect_name(step.effect, step.params)}: held-out RMSE "
        f"{um_text(step.before.rmse_um)} µm → {um_text(step.after.rmse_um)} µm "
        f"({change_text(step.rmse_gain_pct)} %)."
    )


def step_heading(step: StepResult) -> str:
    if step.effect == "none":
        return f"Step {step.number}: nothing added"
    return f"Step {step.number}: added {effect_name(step.effect, step.params)}"


# --------------------------------------------------------------------------- table rows


@dataclass(frozen=True)
class Row:
    """One table row as the strings both layouts show; ``chosen`` marks the added candidate."""

    cells: tuple[str, ...]
    chosen: bool = False


def candidate_cells(cand: CandidateResult, chosen: bool) -> tuple[str, ...]:
    return (
        "*" if chosen else "",
        cand.effect,
        params_text(cand.params) or "—",
        um_text(cand.rmse_um),
        change_text(cand.rmse_gain_pct),
        change_text(cand.shape_gain_pct),
        f"{cand.folds_improved}/{cand.folds}",
        p_text(cand.p_value),
        "yes" if cand.believed else "no",
        cand.reason,
    )


def candidate_rows(step: StepResult, order: str = "tried") -> list[Row]:
    """The round's candidates, in the order tried or (``order="rmse"``) best first."""
    chosen = step.chosen_index
    indexed = list(enumerate(step.candidates))
    if order == "rmse":
        indexed.sort(key=lambda item: item[1].rmse_um)
    return [Row(candidate_cells(c, i == chosen), i == chosen) for i, c in indexed]


def accuracy_rows(result: AnalysisResult) -> list[Row]:
    rows = []
    for label, acc in ((before_label(result), result.before), (after_label(result), result.after)):
        cells = (label, um_text(acc.rmse_um), um_text(acc.sigma_um), um_text(acc.max_abs_um))
        rows.append(Row((*cells, str(acc.n_samples))))
    return rows


def run_rows(result: AnalysisResult) -> list[Row]:
    return [
        Row(
            (
                r.run,
                str(r.n_samples),
                um_text(r.rmse_before_um),
                um_text(r.rmse_after_um),
                pct_text(100.0 * r.share_after),
            )
        )
        for r in result.per_run
    ]


def before_label(result: AnalysisResult) -> str:
    return f"before: {result.model}"


def after_label(result: AnalysisResult) -> str:
    effects = result.effects
    return "after: + " + " + ".join(effects) if effects else "after: nothing added"


def facts(result: AnalysisResult) -> list[tuple[str, Any]]:
    """How the figures were obtained (label, value): plain strings or mappings."""
    groups = [(r.run, r.n_samples) for r in result.per_run]
    runs = f"{len(groups)}: " + ", ".join(f"{name} ({n} rows)" for name, n in groups)
    rows: list[tuple[str, Any]] = [
        ("Model", result.model),
        ("Target", result.target),
        ("Sensors", ", ".join(result.sensors) or "—"),
        ("Runs", runs),
        ("Validation", result.validation),
        ("Tolerance", f"held-out RMSE ≤ {um_text(result.tolerance_um)} µm"),
        ("Reference", dict(result.reference)),
        ("Rules", dict(result.rules)),
        ("Source file", result.source or "—"),
        ("Data fingerprint", result.data_fingerprint or "—"),
    ]
    if result.skipped_rows:
        rows.append(("Skipped rows", result.skipped_rows))
    if result.stored_model:
        rows.append(("Stored model", dict(result.stored_model)))
    return rows


# --------------------------------------------------------------------------- layouts


def columns(header: Sequence[str], rows: Sequence[Row], numeric: frozenset[int]) -> list[str]:
    """Rows padded into columns: numbers right-aligned, text left-aligned, two spaces apart."""
    table = [tuple(header), *(row.cells for row in rows)]
    widths = [max(len(line[i]) for line in table) for i in range(len(header))]
    return [
        "  ".join(
            cell.rjust(w) if i in numeric else cell.ljust(w)
            for i, (cell, w) in enumerate(zip(line, widths, strict=True))
        ).rstrip()
        for line in table
    ]


def text_report(result: AnalysisResult) -> str:
    """The terminal layout: rounds with their candidates (best first), then the figures."""
    lines = [
        f"validation: {result.validation}; tolerance: held-out RMSE ≤ "
        f"{um_text(result.tolerance_um)} µm"
    ]
    for step in result.steps:
        before = um_text(step.before.rmse_um)
        lines += ["", f"round {step.number}: held-out RMSE before {before} µm"]
        table = columns(CANDIDATE_HEADER, candidate_rows(step, "rmse"), NUMERIC_CANDIDATE_COLUMNS)
        lines += ["  " + line for line in table]
        lines.append(f"  → {step_text(step)}")
    lines += ["", result.headline, ""]
    numbers = frozenset({1, 2, 3, 4})
    lines += columns(ACCURACY_HEADER, accuracy_rows(result), numbers)
    lines += ["", "per run (held-out):"]
    lines += ["  " + line for line in columns(RUN_HEADER, run_rows(result), numbers)]
    lines += ["", f"next: {result.next_step_text}"]
    if result.added_steps:
        lines.append(
            "note: an effect's entry was judged with every held-out run, the scored ones "
            "included; analyze --nested gives a figure no choice saw"
        )
    if result.base_choice is not None:
        lines.append(f"base: {base_choice_text(result.base_choice)}")
    if result.nested is not None:
        lines += ["", result.nested.to_text(result.tolerance_um)]
    return "\n".join(lines)


def base_choice_text(choice: dict[str, Any]) -> str:
    scores = ", ".join(f"{m} {um_text(v)}" for m, v in choice["heldout_rmse_um"].items())
    return (
        f"every base analysed, held-out RMSE {scores} µm; kept {choice['kept']}, "
        "its figures optimistic by this choice"
    )


def html_report(result: AnalysisResult, plots: Sequence[Any]) -> str:
    """The HTML layout, rendered from the package's Jinja2 template with autoescape on."""
    from jinja2 import Environment, PackageLoader, StrictUndefined

    env = Environment(
        loader=PackageLoader("models", "templates"),
        autoescape=True,
        undefined=StrictUndefined,
        keep_trailing_newline=True,
    )
    env.filters["value"] = value_text
    title = f"Thermal-error analysis: {result.model} → {result.target}"
    steps = [
        {
            "heading": step_heading(step),
            "text": step_text(step),
            "rows": candidate_rows(step),
        }
        for step in result.steps
    ]
    return env.get_template(TEMPLATE).render(
        title=title,
        headline=result.headline,
        next_step=result.next_step_text,
        accuracy_header=ACCURACY_HEADER,
        accuracy_rows=accuracy_rows(result),
        run_header=RUN_HEADER,
        run_rows=run_rows(result),
        facts=facts(result),
        candidate_header=CANDIDATE_HEADER,
        numeric=NUMERIC_CANDIDATE_COLUMNS,
        steps=steps,
        plots=list(plots),
        base_choice=None if result.base_choice is None else base_choice_text(result.base_choice),
        nested=None if result.nested is None else result.nested.tables(result.tolerance_um),
    )
