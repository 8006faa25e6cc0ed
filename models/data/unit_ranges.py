"""What a measured value may physically be, by the unit its column name carries.

A number can parse and still be nonsense: 1e308 °C fits in a float, but a
model fitted on it has an infinite RMSE and the residual analysis cannot even
solve its least squares. Every numeric column with a unit in its name is held
to a range no real machine leaves; the bounds are wide on purpose, to refuse
corrupt or mis-scaled data (a value logged in m°C, a time in ms), never a
real measurement:

========================  =============================  =========================
column                    unit                           accepted
========================  =============================  =========================
``T<n>``, ``*_C``         °C                             -60 … 400
``speed_rpm``, ``*_rpm``  r/min                          0 … 100 000
``*_um``                  µm                             -10 000 … 10 000
``time_s``                s                              -1e10 … 1e10 (317 years)
any other number          (none)                         finite, |x| ≤ 1e12
========================  =============================  =========================
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

SENSOR_PATTERN = re.compile(r"^T\d+$")
TIME_COLUMN = "time_s"


@dataclass(frozen=True)
class Bounds:
    """The closed range a column's values must lie in, and how to say so."""

    low: float
    high: float
    what: str  # e.g. "a temperature in °C"

    def describe(self) -> str:
        return f"{self.what} from {self.low:g} to {self.high:g}"


TEMPERATURE_C = Bounds(-60.0, 400.0, "a temperature in °C")
SPEED_RPM = Bounds(0.0, 100_000.0, "a spindle speed in r/min")
DISPLACEMENT_UM = Bounds(-10_000.0, 10_000.0, "a displacement in µm")
TIME_S = Bounds(-1e10, 1e10, "a time in seconds")
UNITLESS = Bounds(-1e12, 1e12, "a number")


def bounds_of(column: str) -> Bounds:
    """The plausible range of a column, from the unit its name carries."""
    if SENSOR_PATTERN.match(column) or column.endswith("_C"):
        return TEMPERATURE_C
    if column.endswith("_rpm"):
        return SPEED_RPM
    if column.endswith("_um"):
        return DISPLACEMENT_UM
    if column == TIME_COLUMN:
        return TIME_S
    return UNITLESS


def has_unit(column: str) -> bool:
    """True when the name says what the column measures (so it must be numeric)."""
    return bounds_of(column) is not UNITLESS


def first_implausible(values: np.ndarray, bounds: Bounds) -> int | None:
    """Index of the first NaN, infinite or out-of-range value, or None when all are fine."""
    bad = ~((values >= bounds.low) & (values <= bounds.high))  # NaN compares False
    if not bad.any():
        return None
    return int(np.argmax(bad))


def why_implausible(value: float, bounds: Bounds) -> str:
    """The message for one refused value."""
    if not np.isfinite(value):
        return f"expected a finite number ({bounds.describe()}), found '{value!r}'"
    return f"expected {bounds.describe()}, found {value:g}"
