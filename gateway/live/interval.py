"""This cycle's prediction interval and training-span state, from the model in use.

The model document holds its calibrated half-width (:mod:`models.fit.interval`) and
the span of every input it was fitted on (:mod:`models.training_range`). Each cycle
the half-width is widened by how far an input lies beyond that span and by the
sensors flagged bad, exactly as ``score`` widens it offline, and the inputs outside
the span are named. A model stored without a calibration has no interval (None); one
without a training range has an unknown span state.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from gateway.live.bank.model_bank import Banked, BankedModel
from models.fit.interval import span_excess, widened_um

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
    if stored is None:
        excess, outside = 0.0, []
        span = None
    else:
        used = {name: rises_C[name] for name in banked.sensors if name in rises_C}
        excess, outside = span_excess(stored, used, speed_rpm)
        span = OUTSIDE if outside else INSIDE
    width = None if calibration is None else widened_um(calibration, excess, bad_sensors)
    return CycleInterval(width, span, outside)
