"""How an analysis writes its figures: µm, percentages, p-values, parameters, table columns.

The one place a figure becomes text, shared by the results object
(:mod:`models.analysis.result`), its renderers (:mod:`models.analysis.render`) and the
search's progress lines, so the terminal, the HTML report and the JSON's text fields
cannot disagree. Conventions for people: µm to 0.01, percentages to 0.1, a change of
the RMSE signed (−25.5 % is less error), time constants in minutes, p-values to three
significant digits and never 0 (below ``P_FLOOR`` they read "< 1e-16").
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: p-values below this print as "< 1e-16": the F distribution's tail underflows to
#: 0 long before, and no model of thermal data supports more digits.
P_FLOOR = 1e-16


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


@dataclass(frozen=True)
class Row:
    """One table row as the strings both layouts show; ``chosen`` marks the added candidate."""

    cells: tuple[str, ...]
    chosen: bool = False


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
