"""What a model was fitted on: the span of each input, stored with the model.

A model fitted on rises of 0–12 °C and speeds up to 5000 r/min says nothing
trustworthy about a rise of 20 °C or a spindle at 8000 r/min: every method here
extrapolates linearly (or worse, in powers of the speed) outside the data it saw.
``fit`` and ``analyze --store`` therefore store the span of every sensor's rise
and of the speed (field ``training_range``), and ``score`` names each input of
new data that leaves it (:func:`outside`).

A value counts as outside when it passes the training span by more than
``MARGIN_FRACTION`` of the span's width (the width of one sensor's span, at least
``MIN_MARGIN_C`` °C for temperatures): a few per cent beyond the hottest training
sample is the normal spread of another day, not a new regime.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from models.base import ModelInputs

#: How far beyond the training span (as a fraction of its width) still counts as inside.
MARGIN_FRACTION = 0.05
#: The smallest margin on a temperature rise, °C (a sensor that barely moved in training).
MIN_MARGIN_C = 0.5
#: The smallest margin on the speed, r/min.
MIN_MARGIN_RPM = 10.0


def training_range(inputs: ModelInputs) -> dict[str, Any]:
    """The span (min, max) of each sensor's rise (°C) and of the speed (r/min) in ``inputs``."""
    rises = {
        name: _span(np.asarray(inputs.rise_C, dtype=float)[:, j])
        for j, name in enumerate(inputs.sensors)
    }
    return {
        "rise_C": rises,
        "speed_rpm": _span(np.abs(np.asarray(inputs.speed_rpm, dtype=float))),
        "meaning": "min and max of the training rows (rises above each recording's reference)",
    }


def _span(values: np.ndarray) -> list[float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return [0.0, 0.0]
    return [float(finite.min()), float(finite.max())]


@dataclass(frozen=True)
class Excursion:
    """One input of new data outside the training span."""

    name: str  # a sensor, or "speed"
    unit: str  # "°C" (a rise) or "r/min"
    low: float  # the new data's min
    high: float  # the new data's max
    trained: tuple[float, float]  # the training span
    rows: int  # rows outside

    def describe(self) -> str:
        lo, hi = self.trained
        what = "rise" if self.unit == "°C" else "speed"
        return (
            f"{self.name}: {what} {self.low:.4g} … {self.high:.4g} {self.unit} in {self.rows} "
            f"row(s) outside the training span {lo:.4g} … {hi:.4g} {self.unit}"
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "input": self.name,
            "unit": self.unit,
            "min": self.low,
            "max": self.high,
            "trained": list(self.trained),
            "rows_outside": self.rows,
        }


def outside(
    stored: dict[str, Any], rises_C: dict[str, np.ndarray], speed_rpm: np.ndarray | None
) -> list[Excursion]:
    """Every input of new data (rises °C by sensor, the speed or None) outside ``stored``."""
    found = []
    for name, span in stored.get("rise_C", {}).items():
        if name in rises_C:
            found += _excursion(name, "°C", rises_C[name], span, MIN_MARGIN_C)
    if speed_rpm is not None and "speed_rpm" in stored:
        found += _excursion(
            "speed", "r/min", np.abs(speed_rpm), stored["speed_rpm"], MIN_MARGIN_RPM
        )
    return found


def _excursion(
    name: str, unit: str, values: np.ndarray, span: list[float], min_margin: float
) -> list[Excursion]:
    lo, hi = float(span[0]), float(span[1])
    margin = max(MARGIN_FRACTION * (hi - lo), min_margin)
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    out = (values < lo - margin) | (values > hi + margin)
    if not out.any():
        return []
    return [
        Excursion(name, unit, float(values.min()), float(values.max()), (lo, hi), int(out.sum()))
    ]
