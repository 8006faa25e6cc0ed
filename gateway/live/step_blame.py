"""Whose step moved the prediction: one sensor's own, or none.

The prediction rate bound (rule 2 of :mod:`gateway.live.plausibility`) finds a
prediction that moved faster than heat can, between an earlier cycle and this
one, both predicted by the same model. That alone does not say a sensor is
wrong, and holding a sound one costs the compensation: the model store has a
model without each sensor, not without each pair. A model fitted without T5
leans on T3 by 5.9 µm/°C where the full model leans by 0.3: one 0.1 °C register
step on five of its sensors at once moved it 1.15 µm in 1 s, past the 1.1 µm
bound at a 1 s cycle, and "the sensor that undoes most of the move" was a sound
T3 that had moved by one register step. A restart of the transmitters whose
temperatures came back at another level moved every rise at once, and the
sensor that undid most was held, then the next one under the model without it.

So a sensor is blamed only for a step of its own:

- **its change disagrees with its neighbours' changes.** With the stored
  relations, the change of its rise over the span is judged against what the
  other sensors' changes say, ``z = (Δr_i − Σ b_j Δr_j) / σ_Δ``: the relation
  without its intercept, as on a warm reference, σ_Δ = max(√2 σ_held-out,
  ``min_sigma_C``), the same threshold as rule 1. Without a relation for it, its
  change must exceed ``sigma × min_sigma_C`` (the threshold's worth of the σ
  floor: a few register steps are noise) and fewer than half of the other
  sensors may have moved the same way by half as much;
- **and its own contribution explains the move**: with its rise put back to its
  earlier value, the move is within the bound.

Of the sensors meeting both, the one whose rise put back leaves the smallest
move is blamed. When none does, the move is no sensor's own step: heat the
sensors agree on, the noise of a model with large coefficients, or a step most
of them share (:func:`shared_step`: a restart, a re-zero). Then nobody is held
and the rate bound takes this cycle as its new reference.

Plain numbers in, a verdict out; no state, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from gateway.limits import PlausibilityLimits
from models.estimators.sensor_relations import SensorRelations

__all__ = [
    "Attribution",
    "attribute",
    "changes",
    "is_own_step",
    "jump_floor_C",
    "own_step_z",
    "shared_step",
]

#: Fewest other sensors, trusted at both ends of the span, to judge a change by.
MIN_NEIGHBOURS = 2


@dataclass(frozen=True)
class Attribution:
    """The sensor whose own step explains the move (None: no sensor's), and why."""

    sensor: str | None
    account: str
    #: How many sensors moved beyond the noise floor the same way (a restart: most of them).
    together: int = 0


def changes(now_C: Mapping[str, float], then_C: Mapping[str, float]) -> dict[str, float]:
    """Each sensor's change of rise over the span (°C), for the sensors known at both ends."""
    return {s: now_C[s] - then_C[s] for s in now_C if s in then_C}


def jump_floor_C(limits: PlausibilityLimits) -> float:
    """A change below this (°C) is a few register steps: noise, nobody's step."""
    return limits.sigma * limits.min_sigma_C


def own_step_z(
    relations: SensorRelations | None,
    limits: PlausibilityLimits,
    sensor: str,
    moved_C: Mapping[str, float],
) -> float | None:
    """z of ``sensor``'s change against its neighbours' changes (None: no relation for it)."""
    if relations is None or sensor not in relations.sensors:
        return None
    others = {s: v for s, v in moved_C.items() if s != sensor and s in relations.sensors}
    if len(others) < MIN_NEIGHBOURS:
        return None
    said = relations.predict(sensor, others)
    expected = said.predicted_rise_C - said.intercept_C  # a change: the constant cancels
    sigma = max(math.sqrt(2.0) * said.sigma_C, limits.min_sigma_C)
    return (moved_C[sensor] - expected) / sigma


def shared_step(limits: PlausibilityLimits, sensor: str, moved_C: Mapping[str, float]) -> bool:
    """Whether at least half of the other sensors (two or more) moved as ``sensor`` did:
    the same way, by at least half as much and by more than the noise floor."""
    own = moved_C[sensor]
    floor = max(0.5 * abs(own), jump_floor_C(limits))
    others = [v for s, v in moved_C.items() if s != sensor]
    along = sum(1 for v in others if v * own > 0 and abs(v) > floor)
    return len(others) >= MIN_NEIGHBOURS and along >= max(MIN_NEIGHBOURS, len(others) / 2)


def is_own_step(
    relations: SensorRelations | None,
    limits: PlausibilityLimits,
    sensor: str,
    moved_C: Mapping[str, float],
) -> tuple[bool, str]:
    """(whether ``sensor``'s change is a step of its own, a readable account)."""
    z = own_step_z(relations, limits, sensor, moved_C)
    if z is not None:
        return abs(z) > limits.sigma, f"{moved_C[sensor]:+.2f} °C, {z:+.1f}σ from its neighbours'"
    if abs(moved_C[sensor]) <= jump_floor_C(limits):
        return False, f"{moved_C[sensor]:+.2f} °C, within the noise"
    if shared_step(limits, sensor, moved_C):
        return False, f"{moved_C[sensor]:+.2f} °C, shared by most sensors"
    return True, f"{moved_C[sensor]:+.2f} °C, its own"


def attribute(
    relations: SensorRelations | None,
    limits: PlausibilityLimits,
    sensors: Sequence[str],
    now_C: Mapping[str, float],
    then_C: Mapping[str, float],
    allowed_um: float,
    predict: Callable[[np.ndarray], np.ndarray],
) -> Attribution:
    """The sensor whose own step explains the move of a model's prediction, if any.

    ``sensors``: the model's, in its order; ``now_C`` and ``then_C``: the trusted
    rises of this cycle and of the earlier one (every sensor of the model in
    both, others too); ``predict`` maps (n, len(sensors)) rows to predictions.
    """
    moved_C = changes(now_C, then_C)
    now_x = np.array([now_C[s] for s in sensors])
    rows = np.tile(now_x, (len(sensors) + 1, 1))
    for k, s in enumerate(sensors):
        rows[k + 1, k] = then_C[s]
    rows[0] = [then_C[s] for s in sensors]
    predicted = predict(np.vstack([now_x, rows]))
    left_um = np.abs(predicted[2:] - predicted[1])
    best: tuple[float, str] | None = None
    notes: list[str] = []
    for k, sensor in enumerate(sensors):
        own, account = is_own_step(relations, limits, sensor, moved_C)
        explains = bool(left_um[k] <= allowed_um)
        if own and explains and (best is None or left_um[k] < best[0]):
            best = (float(left_um[k]), sensor)
        if own or explains:
            notes.append(f"{sensor} {account}" + ("" if explains else ", not enough alone"))
    if best is not None:
        return Attribution(best[1], "", stepped_together(limits, moved_C))
    account = "; ".join(notes) if notes else "every change agrees with its neighbours'"
    return Attribution(None, account, stepped_together(limits, moved_C))


def stepped_together(limits: PlausibilityLimits, moved_C: Mapping[str, float]) -> int:
    """How many sensors moved beyond the noise floor in the direction most of them moved."""
    floor = jump_floor_C(limits)
    up = sum(1 for v in moved_C.values() if v > floor)
    down = sum(1 for v in moved_C.values() if v < -floor)
    return max(up, down)
