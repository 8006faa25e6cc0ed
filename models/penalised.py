"""Regularised linear models on temperature rises: ridge and partial least squares.

Both predict ``e = b0 + Σ b_i ΔT_i`` like :mod:`models.mlr`, and store the same
explicit intercept and coefficients, so the runtime, the store and residual
analysis treat them alike. They differ in how the coefficients are found when
the rises are nearly collinear (they always are on one spindle):

- **ridge** shrinks the coefficients of the standardised rises by a penalty α:
  the large balanced pairs of plain least squares (+20 / −13 µm/°C) cost more
  than they gain, so a bias on one sensor moves the compensation far less;
- **pls** regresses on the few latent components of the rises that covary
  most with the error (scikit-learn's ``PLSRegression``).

The penalty (or the number of components) is chosen inside ``fit`` by nested
validation on the training data alone: leave-one-run-out over the runs it is
given (contiguous blocks when it is given one run), lowest pooled held-out
squared error. The validation around ``fit`` therefore never sees the held-out
run when the choice is made.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from models.base import ModelInputs
from models.mlr import MlrModel

#: Penalties tried by ridge, on standardised rises (α relative to the row count).
RIDGE_ALPHAS = tuple(float(a) for a in np.logspace(-4, 2, 25))
#: Most latent components PLS may use.
PLS_MAX_COMPONENTS = 8
#: Blocks of the inner split when the training data hold one run.
INNER_BLOCKS = 5


def inner_groups(inputs: ModelInputs) -> np.ndarray:
    """Group label of each row for the nested choice: its run, or a contiguous block."""
    n = inputs.n_samples
    if inputs.run_index is not None and np.unique(inputs.run_index).size >= 2:
        return np.asarray(inputs.run_index)
    return np.minimum(np.arange(n) * INNER_BLOCKS // max(n, 1), INNER_BLOCKS - 1)


def _choose(estimator: Any, grid: dict[str, list[Any]], X: np.ndarray, y: np.ndarray, groups):
    """The grid value with the lowest leave-one-group-out squared error."""
    from sklearn.model_selection import GridSearchCV, LeaveOneGroupOut

    search = GridSearchCV(
        estimator, grid, cv=LeaveOneGroupOut(), scoring="neg_mean_squared_error", refit=True
    )
    search.fit(X, y, groups=groups)
    return search.best_estimator_, search.best_params_


class _PenalisedLinear(MlrModel):
    """Shared storage of a linear model whose coefficients come from a tuned estimator."""

    choice_key: str  # the tuned hyperparameter's name in ``fitted_params``

    def __init__(self, sensors: Sequence[str] | None = None) -> None:
        super().__init__(sensors)

    def _fit(self, inputs: ModelInputs, error_um: np.ndarray) -> None:
        used = tuple(self.sensors) if self.sensors is not None else inputs.sensors
        X = inputs.columns(used)
        estimator, choice = self._tuned(X, error_um, inner_groups(inputs))
        # Read the fitted linear map back as an explicit intercept and coefficients.
        probe = np.vstack([np.zeros(len(used)), np.eye(len(used))])
        values = np.ravel(estimator.predict(probe))
        self.intercept_um_ = float(values[0])
        self.coef_um_per_C_ = values[1:] - values[0]
        self.sensors_used_ = used
        self.choice_ = choice

    def _tuned(self, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> tuple[Any, float]:
        raise NotImplementedError

    #: The penalised coefficients depend on the data fitted, and so does the design below.
    fixed_design = False

    def design_matrix(self, inputs: ModelInputs) -> np.ndarray:
        """One column: the fitted prediction, µm.

        Residual analysis refits its base terms by least squares jointly with a
        candidate's; refitting the sensors' coefficients without their penalty would
        undo it (the analysis of a ridge base was the analysis of mlr), so the
        analysis scales the penalised prediction instead (coefficient ≈ 1).
        """
        return self.predict(inputs)[:, None]

    def conditioning_design(self, inputs: ModelInputs) -> tuple[np.ndarray, list[str]]:
        """The rises of the sensors read, for the condition number and VIF."""
        return inputs.columns(self.sensors_used_), list(self.sensors_used_)

    def fitted_params(self) -> dict[str, Any]:
        return {**super().fitted_params(), self.choice_key: self.choice_}

    def _load_params(self, params: dict[str, Any]) -> None:
        super()._load_params(params)
        self.choice_ = params[self.choice_key]

    def summary(self) -> str:
        return f"{super().summary()}   [{self.choice_key} {self.choice_:.4g}, nested]"


class RidgeModel(_PenalisedLinear):
    """Ridge regression on standardised rises, penalty chosen by nested validation."""

    method = "ridge"
    choice_key = "penalty"

    def _tuned(self, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> tuple[Any, float]:
        from sklearn.linear_model import Ridge
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        alpha = ridge_penalty(X, y, groups)
        n = X.shape[0]
        best = make_pipeline(StandardScaler(), Ridge(alpha=alpha * n)).fit(X, y)
        return best, alpha


def ridge_penalty(X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> float:
    """The ``RIDGE_ALPHAS`` value with the lowest leave-one-group-out squared error.

    One SVD per held-out group gives the predictions for every penalty at once
    (the same solution scikit-learn's ``Ridge`` finds on the standardised rises).
    """
    alphas = np.asarray(RIDGE_ALPHAS)
    sse = np.zeros(alphas.size)
    for group in np.unique(groups):
        test = groups == group
        train = ~test
        mean = X[train].mean(axis=0)
        scale = X[train].std(axis=0)
        scale[scale == 0] = 1.0
        Z = (X[train] - mean) / scale
        y_mean = y[train].mean()
        U, s, Vt = np.linalg.svd(Z, full_matrices=False)
        Uy = U.T @ (y[train] - y_mean)
        Zt = (X[test] - mean) / scale @ Vt.T
        n = Z.shape[0]
        for i, alpha in enumerate(alphas):
            shrink = s / (s**2 + alpha * n)
            predicted = y_mean + Zt @ (shrink * Uy)
            sse[i] += float(np.sum((y[test] - predicted) ** 2))
    return float(alphas[int(np.argmin(sse))])


class PlsModel(_PenalisedLinear):
    """Partial least squares on scaled rises, component count chosen by nested validation."""

    method = "pls"
    choice_key = "components"

    def _tuned(self, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> tuple[Any, float]:
        from sklearn.cross_decomposition import PLSRegression

        top = max(1, min(PLS_MAX_COMPONENTS, X.shape[1]))
        grid = {"n_components": list(range(1, top + 1))}
        best, params = _choose(PLSRegression(scale=True), grid, X, y, groups)
        return best, int(params["n_components"])
