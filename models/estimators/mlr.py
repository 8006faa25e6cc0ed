"""Multiple linear regression on temperature rises.

    e = b0 + Σ_i b_i ΔT_i          (e in µm, ΔT_i in °C, b_i in µm/°C)

Paper 002 §4 fits exactly this on the temperature-sensitive points
(e.g. Y1 = 6.97 + 4.64 ΔT1 − 2.10 ΔT7). Solved by ordinary least squares
(LAPACK ``gelsd``, SVD based, so a rank-deficient set of sensors still
gives the minimum-norm solution instead of failing).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.linalg.lapack import get_lapack_funcs

from models.base import ModelInputs, ThermalModel


def least_squares_with_intercept(
    X: np.ndarray, y: np.ndarray, rows: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """(b0, b) minimising ‖y − b0 − X b‖², on ``rows`` of X and y only if given.

    LAPACK ``gelsd`` with the rank cutoff of ``numpy.linalg.lstsq(rcond=None)``
    (eps · max(n, k)), on a design built once in Fortran order and solved in
    place. ``numpy.linalg.lstsq`` (and ``scipy.linalg.lstsq``) would copy the
    design first, and on a million-row file that copy is hundreds of megabytes.
    """
    index = None if rows is None else np.flatnonzero(rows)
    n = y.shape[0] if index is None else index.size
    columns = X.shape[1] + 1
    design = np.empty((n, columns), order="F")
    design[:, 0] = 1.0
    rhs = np.zeros(max(n, columns))
    # Column by column, straight into place: no (n, k) temporary of the chosen rows.
    targets = [(X[:, j], design[:, j + 1]) for j in range(X.shape[1])] + [(y, rhs[:n])]
    for source, target in targets:
        if index is None:
            target[:] = source
        else:
            np.take(source, index, axis=0, out=target)
        if not np.all(np.isfinite(target)):
            raise ValueError("fit needs finite temperatures and errors (found NaN or inf)")
    cond = np.finfo(float).eps * max(n, columns)
    gelsd, gelsd_lwork = get_lapack_funcs(("gelsd", "gelsd_lwork"), (design, rhs))
    work, iwork, info = gelsd_lwork(n, columns, 1, cond)
    coef, _, _, info = gelsd(design, rhs, int(work), int(iwork), cond, overwrite_a=1, overwrite_b=1)
    if info > 0:
        raise np.linalg.LinAlgError("SVD did not converge in linear least squares")
    return float(coef[0]), coef[1:columns]


class MlrModel(ThermalModel):
    """Linear in the rises of the declared sensors (default: every input sensor)."""

    method = "mlr"
    fixed_design = True

    def __init__(self, sensors: Sequence[str] | None = None) -> None:
        self.sensors = None if sensors is None else list(sensors)

    def hyperparams(self) -> dict[str, Any]:
        return {"sensors": self.sensors}

    def _fit(self, inputs: ModelInputs, error_um: np.ndarray) -> None:
        used = tuple(self.sensors) if self.sensors is not None else inputs.sensors
        self.intercept_um_, self.coef_um_per_C_ = least_squares_with_intercept(
            inputs.columns(used), error_um
        )
        self.sensors_used_ = used

    def fit_rows(self, inputs: ModelInputs, error_um: np.ndarray, rows: np.ndarray) -> MlrModel:
        """``fit`` on ``rows``, reading them straight from ``inputs`` into the design.

        Only for least squares on the declared sensors: a subclass that chooses its
        sensors or penalises its coefficients (grey-mlr, ridge, pls) fits its own way
        on the rows taken.
        """
        if type(self)._fit is not MlrModel._fit:
            return super().fit_rows(inputs, error_um, rows)
        used = tuple(self.sensors) if self.sensors is not None else inputs.sensors
        y = np.asarray(error_um, dtype=float)
        if y.shape != (inputs.n_samples,):
            raise ValueError(f"error_um must be ({inputs.n_samples},), got {y.shape}")
        self.intercept_um_, self.coef_um_per_C_ = least_squares_with_intercept(
            inputs.columns(used), y, rows
        )
        self.sensors_used_ = used
        return self

    def _predict(self, inputs: ModelInputs) -> np.ndarray:
        return self.intercept_um_ + inputs.columns(self.sensors_used_) @ self.coef_um_per_C_

    def design_matrix(self, inputs: ModelInputs) -> np.ndarray:
        return inputs.columns(self.sensors_used_)

    def fitted_params(self) -> dict[str, Any]:
        return {
            "sensors": list(self.sensors_used_),
            "intercept_um": self.intercept_um_,
            "coefficients_um_per_C": [float(b) for b in self.coef_um_per_C_],
        }

    def _load_params(self, params: dict[str, Any]) -> None:
        self.intercept_um_ = float(params["intercept_um"])
        self.coef_um_per_C_ = np.asarray(params["coefficients_um_per_C"], dtype=float)
        self.sensors_used_ = tuple(params["sensors"])
        if len(self.sensors_used_) != self.coef_um_per_C_.size:
            raise ValueError("mlr: one coefficient per sensor was expected")

    def summary(self) -> str:
        terms = " ".join(
            f"{b:+.4g}·Δ{name}"
            for name, b in zip(self.sensors_used_, self.coef_um_per_C_, strict=True)
        )
        return f"e [µm] = {self.intercept_um_:.4g} {terms}   (ΔT in °C)"
