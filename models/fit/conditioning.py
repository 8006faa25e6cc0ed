"""How well a fit is determined, and how much a biased sensor moves its compensation.

Temperatures on one spindle rise together, so the columns of a regression on
them are nearly collinear. Least squares then balances large coefficients of
opposite sign (e.g. +20 µm/°C on one sensor, −13 µm/°C on its neighbour): the
fit is as good as any on the training data, but a small bias on one sensor —
one that passes every range, rate and stuck check — moves the compensation by
many µm. Three figures say so before such a model reaches a machine:

- **condition number** of the design, its columns centred and scaled to unit
  norm (Belsley's scaling, intercept left out): ≲ 30 is well determined,
  ≳ 100 means the data cannot separate the inputs;
- **variance inflation factor** (VIF) of each input, 1 / (1 − R²) of that input
  regressed on the others: how much its coefficient's variance is inflated by
  collinearity (> 10 is the usual alarm);
- **bias sensitivity** of each sensor: µm of predicted error per °C of constant
  bias on that sensor, the mean of ∂prediction/∂ΔT over the training rows (for a
  linear model, its coefficient). For a stated sensor accuracy ±a °C, the
  **worst single sensor** moves the compensation by ``a · max|s_i|`` and the
  **worst case** (every sensor off by a, each in the adverse direction) by
  ``a · Σ|s_i|``. The runtime refuses models whose worst case exceeds the
  configured limit.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from models.base import ModelInputs, ThermalModel
from models.catalogue import DEFAULT_MAX_BIAS_ERROR_UM as DEFAULT_MAX_BIAS_ERROR_UM
from models.catalogue import DEFAULT_SENSOR_ACCURACY_C as DEFAULT_SENSOR_ACCURACY_C

#: Finite-difference step for models whose prediction is not linear in the rises.
_STEP_C = 0.1


@dataclass(frozen=True)
class Conditioning:
    """Conditioning and bias sensitivity of one fitted model.

    Attributes:
        inputs: names of the design's columns (sensor rises, speed terms).
        condition_number: of the centred, unit-norm design (no intercept).
        vif: variance inflation factor per input, same order as ``inputs``.
        sensitivity_um_per_C: µm of compensation per °C of bias, per sensor.
        sensor_accuracy_C: the stated accuracy the worst cases are for.
    """

    inputs: tuple[str, ...]
    condition_number: float
    vif: tuple[float, ...]
    sensitivity_um_per_C: dict[str, float]
    sensor_accuracy_C: float

    @property
    def worst_sensor(self) -> str | None:
        if not self.sensitivity_um_per_C:
            return None
        return max(self.sensitivity_um_per_C, key=lambda s: abs(self.sensitivity_um_per_C[s]))

    @property
    def worst_single_um(self) -> float:
        """Compensation error from the worst sensor off by its accuracy, µm."""
        values = [abs(v) for v in self.sensitivity_um_per_C.values()]
        return self.sensor_accuracy_C * max(values, default=0.0)

    @property
    def worst_case_um(self) -> float:
        """Compensation error with every sensor off by its accuracy, adversely, µm."""
        return self.sensor_accuracy_C * float(
            sum(abs(v) for v in self.sensitivity_um_per_C.values())
        )

    def as_dict(self) -> dict[str, Any]:
        """JSON-safe: an infinite condition number or VIF (inseparable inputs) is null."""
        return {
            "condition_number": _finite_or_none(self.condition_number),
            "vif": {n: _finite_or_none(v) for n, v in zip(self.inputs, self.vif, strict=True)},
            "sensitivity_um_per_C": dict(self.sensitivity_um_per_C),
            "sensor_accuracy_C": self.sensor_accuracy_C,
            "worst_sensor": self.worst_sensor,
            "worst_single_um": self.worst_single_um,
            "worst_case_um": self.worst_case_um,
        }

    def table(self) -> str:
        """Plain-text table: one row per input."""
        lines = [
            f"conditioning: condition number {self.condition_number:.4g} "
            "(centred, unit-norm design; > 100: the data cannot separate the inputs)",
            f"{'input':<14} {'VIF':>10} {'µm per °C bias':>15}",
        ]
        for name, vif in zip(self.inputs, self.vif, strict=True):
            sens = self.sensitivity_um_per_C.get(name)
            shown = "" if sens is None else f"{sens:+.3f}"
            lines.append(f"{name:<14} {vif:>10.4g} {shown:>15}")
        a = self.sensor_accuracy_C
        lines.append(
            f"bias of ±{a:g} °C: worst sensor ({self.worst_sensor}) "
            f"{self.worst_single_um:.2f} µm; every sensor adversely {self.worst_case_um:.2f} µm"
        )
        return "\n".join(lines)


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def condition_number(design: np.ndarray) -> float:
    """Condition number of ``design`` with its columns centred and scaled to unit norm."""
    X = np.asarray(design, dtype=float)
    if X.ndim != 2 or X.shape[1] == 0:
        return 1.0
    with np.errstate(all="ignore"):
        centred = X - X.mean(axis=0)
        norms = np.linalg.norm(centred, axis=0)
        if np.any(norms == 0) or not np.all(np.isfinite(norms)):
            return float("inf")  # constant (or overflowing) columns cannot be separated
        scaled = centred / norms
    if not np.all(np.isfinite(scaled)):
        return float("inf")
    try:
        s = np.linalg.svd(scaled, compute_uv=False)
    except np.linalg.LinAlgError:
        return float("inf")
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def variance_inflation(design: np.ndarray) -> np.ndarray:
    """VIF of each column: the diagonal of the inverse correlation matrix."""
    X = np.asarray(design, dtype=float)
    k = X.shape[1]
    if k == 0:
        return np.zeros(0)
    if k == 1:
        return np.ones(1)
    with np.errstate(all="ignore"):
        centred = X - X.mean(axis=0)
        norms = np.linalg.norm(centred, axis=0)
    vif = np.full(k, np.inf)
    ok = (norms > 0) & np.isfinite(norms) & np.all(np.isfinite(centred), axis=0)
    if ok.sum() >= 1:
        scaled = centred[:, ok] / norms[ok]
        corr = scaled.T @ scaled
        with contextlib.suppress(np.linalg.LinAlgError):  # singular: every VIF stays inf
            vif[ok] = np.diag(np.linalg.inv(corr))
    return vif


def bias_sensitivity(model: ThermalModel, inputs: ModelInputs) -> dict[str, float]:
    """µm of predicted error per °C of constant bias on each sensor the model reads.

    Exact for models linear in the rises; for others, the mean over ``inputs``
    of a central difference of ``_STEP_C``.
    """
    sensors = tuple(model.sensors_used_)
    columns = [inputs.sensors.index(s) for s in sensors]
    out: dict[str, float] = {}
    for name, col in zip(sensors, columns, strict=True):
        up = inputs.rise_C.copy()
        down = inputs.rise_C.copy()
        up[:, col] += _STEP_C
        down[:, col] -= _STEP_C
        shifted_up = ModelInputs(up, inputs.sensors, inputs.speed_rpm, inputs.run_index)
        shifted_down = ModelInputs(down, inputs.sensors, inputs.speed_rpm, inputs.run_index)
        slope = (model.predict(shifted_up) - model.predict(shifted_down)) / (2 * _STEP_C)
        out[name] = float(np.mean(slope))
    return out


def design_for_conditioning(model: ThermalModel, inputs: ModelInputs) -> tuple[np.ndarray, list]:
    """The model's own design (its terms) with names, or the rises of the sensors it reads."""
    sensors = list(model.sensors_used_)
    own = getattr(model, "conditioning_design", None)
    if callable(own):  # a model whose design_matrix is not its terms (models.estimators.lag_ridge)
        return own(inputs)
    try:
        design = model.design_matrix(inputs)
    except NotImplementedError:
        return inputs.columns(tuple(sensors)), sensors
    if len(sensors) == design.shape[1]:
        return design, sensors
    return design, [f"term{i + 1}" for i in range(design.shape[1])]


def assess(
    model: ThermalModel,
    inputs: ModelInputs,
    sensor_accuracy_C: float = DEFAULT_SENSOR_ACCURACY_C,
) -> Conditioning:
    """Conditioning and bias sensitivity of ``model`` on the data it was fitted on."""
    if not (np.isfinite(sensor_accuracy_C) and sensor_accuracy_C > 0):
        raise ValueError(f"sensor_accuracy_C must be > 0, got {sensor_accuracy_C}")
    design, names = design_for_conditioning(model, inputs)
    return Conditioning(
        inputs=tuple(names),
        condition_number=condition_number(design),
        vif=tuple(float(v) for v in variance_inflation(design)),
        sensitivity_um_per_C=bias_sensitivity(model, inputs),
        sensor_accuracy_C=float(sensor_accuracy_C),
    )


def worst_case_from_record(record: dict[str, Any], sensor_accuracy_C: float) -> float | None:
    """Worst-case µm for ``sensor_accuracy_C`` from a stored ``conditioning`` record."""
    sens = record.get("sensitivity_um_per_C") if record else None
    if not sens:
        return None
    return float(sensor_accuracy_C) * float(sum(abs(float(v)) for v in sens.values()))
