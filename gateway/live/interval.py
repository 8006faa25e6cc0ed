"""This cycle's prediction interval and training-span state, from the model in use.

The model document holds its calibrated half-width (:mod:`models.fit.interval`) and
the span of every input it was fitted on (:mod:`models.training_range`). Each cycle
the half-width is widened by how far an input lies beyond that span and by the
sensors flagged bad, exactly as ``score`` widens it offline, and the inputs outside
the span are named. With the online correction running, the loop widens it further
by the variance the correction gained since the last probe
(:func:`models.fit.interval.with_probe_age`). A model stored without a calibration
has no interval (None); one without a training range has an unknown span state.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from gateway.live.bank.model_bank import Banked, BankedModel
from models.fit.interval import NOMINAL_COVERAGE, widened_um
from models.training_range import MARGIN_FRACTION, MIN_MARGIN_C, MIN_MARGIN_RPM

INSIDE = "inside"
OUTSIDE = "outside"


@dataclass(frozen=True)
class CycleInterval:
    """The half-width of this cycle's interval (µm) and the training-span state."""

    half_width_um: float | None = None
    span: str | None = None  # "inside", "outside", or None (no model or no span stored)
    outside_inputs: list[str] = field(default_factory=list)


def stored_of(banked: Banked) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """(the calibration, the training range) a banked model holds, each None if absent."""
    if isinstance(banked, BankedModel):
        return banked.document.interval, banked.document.training_range
    return banked.interval, banked.training_range


def interval_nominal(banked: Banked | None) -> float:
    """The nominal coverage of the model's calibration (the default when it holds none)."""
    calibration = None if banked is None else stored_of(banked)[0]
    return float((calibration or {}).get("nominal_coverage", NOMINAL_COVERAGE))


#: One input's bounds: (name, lowest inside, highest inside, the excess's divisor).
Bounds = tuple[str, float, float, float]
#: Compiled spans by stored training range (kept with it, so its id stays its own).
_compiled: dict[int, tuple[dict[str, Any], list[Bounds]]] = {}


def _bounds(name: str, span: list[float], min_margin: float) -> Bounds:
    """The bounds :func:`models.fit.interval.excess_fraction` compares with, computed once."""
    lo, hi = float(span[0]), float(span[1])
    margin = max(MARGIN_FRACTION * (hi - lo), min_margin)
    return (name, lo - margin, hi + margin, max(hi - lo, margin))


def compiled(stored: dict[str, Any]) -> list[Bounds]:
    """Each input's bounds of ``stored`` (the sensors, then ``speed``), built once per range."""
    known = _compiled.get(id(stored))
    if known is None or known[0] is not stored:
        bounds = [_bounds(n, span, MIN_MARGIN_C) for n, span in stored.get("rise_C", {}).items()]
        if "speed_rpm" in stored:
            bounds.append(_bounds("speed", stored["speed_rpm"], MIN_MARGIN_RPM))
        known = _compiled[id(stored)] = (stored, bounds)
    return known[1]


def excess_of(
    stored: dict[str, Any], rises_C: Mapping[str, float], speed_rpm: float | None
) -> tuple[float, list[str]]:
    """(largest excess beyond the span, the inputs outside it): the same figures as
    :func:`models.fit.interval.span_excess`, with the bounds computed once per model."""
    largest = 0.0
    names: list[str] = []
    for name, low, high, divisor in compiled(stored):
        value = abs(speed_rpm) if name == "speed" and speed_rpm is not None else rises_C.get(name)
        if value is None or not low <= value <= high:
            if value is None or value != value:  # absent or NaN: not judged
                continue
            names.append(name)
            largest = max(largest, max(low - value, value - high) / divisor)
    return largest, names


def assess(
    banked: Banked | None,
    predicted_um: float | None,
    rises_C: Mapping[str, float],
    speed_rpm: float | None,
    bad_sensors: int,
) -> CycleInterval:
    """This cycle's interval around ``predicted_um`` and whether its inputs are inside the
    model's training span (the model's own sensors and the speed)."""
    if banked is None or predicted_um is None:
        return CycleInterval()
    calibration, stored = stored_of(banked)
    outside: list[str] = []
    if stored is None:
        excess = 0.0
        span = None
    else:
        used = {name: rises_C[name] for name in banked.sensors if name in rises_C}
        excess, outside = excess_of(stored, used, speed_rpm)
        span = OUTSIDE if outside else INSIDE
    width = None if calibration is None else widened_um(calibration, excess, bad_sensors)
    return CycleInterval(width, span, outside)
