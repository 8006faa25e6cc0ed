"""PCA + full quadratic regression in speed (paper 000, Wang & Wu 2026, §2.2–3.1).

1. PCA on the correlation matrix of the chosen sensors' temperature rises
   (:mod:`models.estimators.parts.pca`); keep the first m components whose cumulative
   contribution reaches the threshold (85 %). Scores x1 … xm are dimensionless.
2. Add the spindle speed x_{m+1} = speed_rpm / 1000, in 1000 r/min
   ("speed_krpm"). The paper never states the unit of its speed input; here it
   is fixed so the coefficients have a stated meaning.
3. Fit the full quadratic in [x1 … xm, speed_krpm] (MATLAB rstool
   ``'quadratic'``, :mod:`models.estimators.parts.quadratic`) to the thermal error by least
   squares; every coefficient is in µm per unit of its term.

With m = 2 this is the paper's 10-term model
y = b0 + b1 x1 + b2 x2 + b3 x3 + b12 x1x2 + b13 x1x3 + b23 x2x3 + b11 x1² + b22 x2² + b33 x3².
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from models.base import ModelInputs, ThermalModel
from models.estimators.parts.pca import ConstantVariableError, PcaResult, correlation_pca
from models.estimators.parts.quadratic import (
    fit_least_squares,
    n_quadratic_terms,
    quadratic_design,
    quadratic_terms,
)

SPEED_INPUT = "speed_krpm"
SPEED_SCALE_RPM = 1000.0  # speed_krpm = speed_rpm / SPEED_SCALE_RPM
SCORE_DESCRIPTION = "principal-component score (dimensionless) of z-scored temperature rises"
SPEED_DESCRIPTION = "spindle speed in 1000 r/min"


class PcaQuadraticModel(ThermalModel):
    """Thermal error (µm) = full quadratic in the kept PCA scores and speed (1000 r/min).

    Args:
        sensors: sensors to reduce by PCA; ``None`` means every input sensor.
        threshold: cumulative contribution the kept components must reach, in (0, 1].

    Fitted attributes: ``sensors_used_``, ``pca_`` (:class:`models.estimators.parts.pca.PcaResult`),
    ``terms_`` (term names) and ``coef_`` (µm per unit of each term).
    """

    method = "pca-quadratic"

    pca_: PcaResult
    terms_: list[str]
    coef_: np.ndarray

    def __init__(self, sensors: Sequence[str] | None = None, threshold: float = 0.85) -> None:
        self.sensors = None if sensors is None else list(sensors)
        self.threshold = threshold

    def hyperparams(self) -> dict[str, Any]:
        return {"sensors": self.sensors, "threshold": float(self.threshold)}

    @property
    def uses_speed(self) -> bool:
        return True

    @property
    def input_names(self) -> list[str]:
        """Regression inputs of the fitted model: x1 … xm, then speed_krpm."""
        return [f"x{i + 1}" for i in range(self.pca_.n_kept)] + [SPEED_INPUT]

    def _fit(self, inputs: ModelInputs, error_um: np.ndarray) -> None:
        names = inputs.sensors if self.sensors is None else tuple(self.sensors)
        if not names:
            raise ValueError("PcaQuadraticModel needs at least one sensor")
        try:
            pca = correlation_pca(inputs.columns(names), self.threshold)
        except ConstantVariableError as err:
            raise ValueError(
                f"sensor {names[err.column]!r} has a constant rise over the fitting data: "
                "PCA cannot z-score it; drop it from the sensors"
            ) from err
        self.pca_ = pca
        self.sensors_used_ = tuple(names)
        self.terms_ = quadratic_terms(self.input_names)
        design = quadratic_design(self._regressors(inputs))
        rank = np.linalg.matrix_rank(design)
        if rank < design.shape[1]:
            warnings.warn(
                f"quadratic design has rank {rank} < {design.shape[1]} terms (too few rows, "
                "or a single speed): least squares returns the minimum-norm solution",
                RuntimeWarning,
                stacklevel=3,
            )
        self.coef_ = fit_least_squares(design, error_um)

    def _regressors(self, inputs: ModelInputs) -> np.ndarray:
        """(n, m + 1): kept component scores, then speed in 1000 r/min."""
        scores = self.pca_.scores(inputs.columns(self.sensors_used_))
        return np.column_stack([scores, inputs.speed_rpm / SPEED_SCALE_RPM])

    def _predict(self, inputs: ModelInputs) -> np.ndarray:
        return quadratic_design(self._regressors(inputs)) @ self.coef_

    def design_matrix(self, inputs: ModelInputs) -> np.ndarray:
        return quadratic_design(self._regressors(inputs))[:, 1:]

    def fitted_params(self) -> dict[str, Any]:
        pca = self.pca_
        units = {name: SCORE_DESCRIPTION for name in self.input_names[:-1]}
        units[SPEED_INPUT] = SPEED_DESCRIPTION
        return {
            "sensors": list(self.sensors_used_),
            "mean_C": pca.mean.tolist(),
            "scale_C": pca.scale.tolist(),
            "eigenvalues": pca.eigenvalues.tolist(),
            "components": pca.components[:, : pca.n_kept].T.tolist(),
            "n_components": pca.n_kept,
            "threshold": pca.threshold,
            "terms": list(self.terms_),
            "coefficients_um": self.coef_.tolist(),
            "inputs": units,
        }

    def _load_params(self, params: dict[str, Any]) -> None:
        sensors = tuple(params["sensors"])
        m = int(params["n_components"])
        mean = np.asarray(params["mean_C"], dtype=float)
        scale = np.asarray(params["scale_C"], dtype=float)
        eigenvalues = np.asarray(params["eigenvalues"], dtype=float)
        components = np.asarray(params["components"], dtype=float).T  # (p, m)
        coef = np.asarray(params["coefficients_um"], dtype=float)
        p = len(sensors)
        if mean.shape != (p,) or scale.shape != (p,) or eigenvalues.shape != (p,):
            raise ValueError(f"mean_C, scale_C and eigenvalues must each have {p} entries")
        if components.shape != (p, m):
            raise ValueError(f"components must be {m} lists of {p} loadings")
        if coef.shape != (n_quadratic_terms(m + 1),) or len(params["terms"]) != coef.size:
            raise ValueError(f"need {n_quadratic_terms(m + 1)} terms and coefficients for m = {m}")
        contribution = eigenvalues / eigenvalues.sum()
        self.pca_ = PcaResult(
            mean=mean,
            scale=scale,
            eigenvalues=eigenvalues,
            components=components,
            contribution=contribution,
            cumulative=np.cumsum(contribution),
            n_kept=m,
            threshold=float(params["threshold"]),
        )
        self.terms_ = list(params["terms"])
        self.coef_ = coef
        self.sensors_used_ = sensors

    def input_units(self) -> dict[str, str]:
        """Units of what ``predict`` reads (sensor rises, speed_rpm) and of the
        regression inputs derived from them (x1 … xm, speed_krpm)."""
        units = super().input_units()
        units.update(
            {name: "dimensionless (principal-component score)" for name in self.input_names[:-1]}
        )
        units[SPEED_INPUT] = "1000 r/min (speed_rpm / 1000)"
        return units

    def summary(self) -> str:
        """Readable text: kept components with their contributions, then every term."""
        pca = self.pca_
        lines = [
            f"PCA + quadratic (paper 000) on {len(self.sensors_used_)} sensors: "
            + ", ".join(self.sensors_used_),
            f"kept {pca.n_kept} component(s), cumulative contribution "
            f"{100 * pca.cumulative[pca.n_kept - 1]:.2f} % (threshold {100 * pca.threshold:.0f} %)",
        ]
        for i in range(pca.n_kept):
            loadings = ", ".join(
                f"{name} {pca.components[j, i]:+.3f}" for j, name in enumerate(self.sensors_used_)
            )
            lines.append(
                f"  x{i + 1}: eigenvalue {pca.eigenvalues[i]:.4f}, "
                f"contribution {100 * pca.contribution[i]:.2f} %; loadings {loadings}"
            )
        lines.append("inputs: x1… dimensionless scores; speed_krpm in 1000 r/min")
        lines.append("error_um =")
        for term, coef in zip(self.terms_, self.coef_, strict=True):
            lines.append(f"  {coef:+.6g} µm  × {term}")
        return "\n".join(lines)
