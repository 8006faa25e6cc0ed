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
#: An eigenvalue of the correlation matrix below this fraction of the largest is taken as
#: a direction the data do not see (rounding makes it either sign).
NULL_EIGENVALUE = 1e-10
#: An input with more than this share of its unit vector in those directions is a
#: combination of the others (rounding puts ~1e-19 there for one that is not).
NULL_SHARE = 1e-9
#: A condition number beyond this is reported as unbounded: the smallest singular value
#: is then within rounding of the largest's scale, and the figure says nothing more.
MAX_CONDITION = 1e8
#: Inputs listed by default, worst VIF first (``fit --collinearity full``: all of them).
SHORT_ROWS = 5


@dataclass(frozen=True)
class Conditioning:
    """Conditioning and bias sensitivity of one fitted model.

    Attributes:
        inputs: names of the design's columns (sensor rises, speed terms).
        condition_number: of the centred, unit-norm design (no intercept), over the
            inputs that vary on the training rows (``inf``: exactly collinear ones).
        vif: variance inflation factor per input, same order as ``inputs`` (≥ 1;
            ``inf``: constant or collinear, not identifiable).
        sensitivity_um_per_C: µm of compensation per °C of bias, per sensor.
        sensor_accuracy_C: the stated accuracy the worst cases are for.
        constant: the inputs that do not vary on the training rows.
    """

    inputs: tuple[str, ...]
    condition_number: float
    vif: tuple[float, ...]
    sensitivity_um_per_C: dict[str, float]
    sensor_accuracy_C: float
    constant: tuple[str, ...] = ()

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

    @property
    def collinear(self) -> tuple[str, ...]:
        """Inputs that vary but are combinations of the others (see :func:`variance_inflation`)."""
        return tuple(
            n for n, v in zip(self.inputs, self.vif, strict=True)
            if not np.isfinite(v) and n not in self.constant
        )  # fmt: skip

    def as_dict(self) -> dict[str, Any]:
        """JSON-safe: an infinite condition number or VIF (inseparable inputs) is null."""
        return {
            "condition_number": _finite_or_none(self.condition_number),
            "vif": {n: _finite_or_none(v) for n, v in zip(self.inputs, self.vif, strict=True)},
            "constant_inputs": list(self.constant),
            "collinear_inputs": list(self.collinear),
            "sensitivity_um_per_C": dict(self.sensitivity_um_per_C),
            "sensor_accuracy_C": self.sensor_accuracy_C,
            "worst_sensor": self.worst_sensor,
            "worst_single_um": self.worst_single_um,
            "worst_case_um": self.worst_case_um,
        }

    def table(self, full: bool = False) -> str:
        """Plain text: the condition number, the worst VIFs (``full``: one row per input
        with its bias sensitivity) and the bias worst cases."""
        lines = [f"conditioning: condition number {self._condition_text()}"]
        if self.constant:
            lines.append(
                f"constant on the training rows (not identifiable): {_names(self.constant)}"
            )
        if self.collinear:
            lines.append(
                "combinations of the other inputs (VIF unbounded, not identifiable): "
                f"{_names(self.collinear)}"
            )
        lines += self._vif_rows(full)
        a = self.sensor_accuracy_C
        lines.append(
            f"bias of ±{a:g} °C: worst sensor ({self.worst_sensor}) "
            f"{self.worst_single_um:.2f} µm; every sensor adversely {self.worst_case_um:.2f} µm"
        )
        return "\n".join(lines)

    def _condition_text(self) -> str:
        note = "(centred, unit-norm design; > 100: the data cannot separate the inputs)"
        if np.isfinite(self.condition_number):
            return f"{self.condition_number:.4g} {note}"
        return f"unbounded (> {MAX_CONDITION:.0e}): inputs are combinations of others {note}"

    def _vif_rows(self, full: bool) -> list[str]:
        """``full``: every input with its VIF and bias sensitivity; else the worst few
        identifiable VIFs and the sensors' sensitivities on one line."""
        width = max([14, *(len(n) for n in self.inputs)])
        if full:
            rows = [f"{'input':<{width}} {'VIF':>10} {'µm per °C bias':>15}"]
            for name, vif in zip(self.inputs, self.vif, strict=True):
                sens = self.sensitivity_um_per_C.get(name)
                shown = "" if sens is None else f"{sens:+.3f}"
                shown_vif = _vif_text(name, vif, self.constant)
                rows.append(f"{name:<{width}} {shown_vif:>10} {shown:>15}")
            return rows
        finite = [(v, n) for n, v in zip(self.inputs, self.vif, strict=True) if np.isfinite(v)]
        worst = sorted(finite, reverse=True)[:SHORT_ROWS]
        alarm = sum(1 for v, _ in finite if v > 10) + len(self.collinear)
        rows = [
            f"VIF > 10 or unbounded on {alarm} of {len(self.inputs)} inputs; worst finite: "
            + (", ".join(f"{n} {v:.3g}" for v, n in worst) or "none")
            + (" (every input: --collinearity full)" if len(self.inputs) > SHORT_ROWS else "")
        ]
        moving = sorted(
            ((s, n) for n, s in self.sensitivity_um_per_C.items() if s != 0),
            key=lambda sn: -abs(sn[0]),
        )
        if moving:
            rows.append(
                "µm per °C bias: "
                + ", ".join(f"{n} {s:+.3f}" for s, n in moving[:SHORT_ROWS])
                + (f" (+{len(moving) - SHORT_ROWS} more)" if len(moving) > SHORT_ROWS else "")
            )
        return rows


def _names(names: tuple[str, ...], most: int = 8) -> str:
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


def _vif_text(name: str, vif: float, constant: tuple[str, ...]) -> str:
    if np.isfinite(vif):
        return f"{vif:.4g}"
    return "constant" if name in constant else "collinear"


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def condition_number(design: np.ndarray) -> float:
    """Condition number of ``design`` with its columns centred and scaled to unit norm
    (``inf`` beyond ``MAX_CONDITION``, or with a constant column)."""
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
    return float(s[0] / s[-1]) if s[-1] * MAX_CONDITION > s[0] else float("inf")


def variance_inflation(design: np.ndarray) -> np.ndarray:
    """VIF of each column: the diagonal of the inverse correlation matrix, ≥ 1 or ``inf``.

    Taken from the eigendecomposition of the correlation matrix, VIF_j = Σ_k v_jk² / λ_k,
    which cannot fall below 1 (unlike a plain inverse of a near-singular matrix, whose
    rounding gives VIFs of either sign). An eigenvalue below ``NULL_EIGENVALUE`` × the
    largest is a direction the data do not see: a column with more than ``NULL_SHARE`` of
    its unit vector in those directions is a combination of the others (``inf``: not
    identifiable), as is a constant column; the others' VIF is taken over the rest.
    """
    X = np.asarray(design, dtype=float)
    k = X.shape[1]
    if k == 0:
        return np.zeros(0)
    with np.errstate(all="ignore"):
        centred = X - X.mean(axis=0)
        norms = np.linalg.norm(centred, axis=0)
    vif = np.full(k, np.inf)
    ok = (norms > 0) & np.isfinite(norms) & np.all(np.isfinite(centred), axis=0)
    if ok.sum() == 1:
        vif[ok] = 1.0
    elif ok.sum() > 1:
        scaled = centred[:, ok] / norms[ok]
        with contextlib.suppress(np.linalg.LinAlgError):  # no decomposition: every VIF inf
            eigenvalues, vectors = np.linalg.eigh(scaled.T @ scaled)
            seen = eigenvalues > NULL_EIGENVALUE * max(float(eigenvalues[-1]), 1e-300)
            unseen_share = (vectors[:, ~seen] ** 2).sum(axis=1)
            values = (vectors[:, seen] ** 2) @ (1.0 / eigenvalues[seen])
            vif[ok] = np.where(unseen_share > NULL_SHARE, np.inf, np.maximum(values, 1.0))
    return vif


def constant_columns(design: np.ndarray) -> np.ndarray:
    """Mask of the columns that do not vary on these rows (nothing to separate them by)."""
    X = np.asarray(design, dtype=float)
    if X.ndim != 2 or X.shape[0] == 0:
        return np.zeros(X.shape[-1] if X.ndim == 2 else 0, dtype=bool)
    with np.errstate(all="ignore"):
        spread = np.nanmax(X, axis=0) - np.nanmin(X, axis=0)
        size = np.maximum(np.nanmax(np.abs(X), axis=0), 1e-300)
    return ~(spread > 1e-12 * size)


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
    constant = constant_columns(design)
    return Conditioning(
        inputs=tuple(names),
        condition_number=condition_number(np.asarray(design)[:, ~constant]),
        vif=tuple(float(v) for v in variance_inflation(design)),
        sensitivity_um_per_C=bias_sensitivity(model, inputs),
        sensor_accuracy_C=float(sensor_accuracy_C),
        constant=tuple(n for n, c in zip(names, constant, strict=True) if c),
    )


def worst_case_from_record(record: dict[str, Any], sensor_accuracy_C: float) -> float | None:
    """Worst-case µm for ``sensor_accuracy_C`` from a stored ``conditioning`` record."""
    sens = record.get("sensitivity_um_per_C") if record else None
    if not sens:
        return None
    return float(sensor_accuracy_C) * float(sum(abs(float(v)) for v in sens.values()))
