"""Regularised linear models on temperature rises: ridge and partial least squares.

Both predict ``e = b0 + Σ b_i ΔT_i`` like :mod:`models.estimators.mlr`, and store the same
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
given (contiguous blocks when it is given one run; above 10 runs, 5 folds of
consecutive runs), lowest pooled held-out squared error. The validation around
``fit`` therefore never sees the held-out run when the choice is made. Every
inner fold is solved from per-run moments (:mod:`models.group_moments`), so the
choice costs one pass over the rows however many runs there are.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from models.base import ModelInputs
from models.estimators.mlr import MlrModel
from models.group_moments import GroupMoments, Moments

#: Penalties tried by ridge, on standardised rises (α relative to the row count).
RIDGE_ALPHAS = tuple(float(a) for a in np.logspace(-4, 2, 25))
#: Most latent components PLS may use.
PLS_MAX_COMPONENTS = 8
#: Blocks of the inner split when the training data hold one run.
INNER_BLOCKS = 5
#: Up to this many training runs the nested choice leaves one run out at a time ...
INNER_GROUPED_ABOVE_RUNS = 10
#: ... above it, this many folds of consecutive runs (the cost stays bounded per fit).
INNER_FOLDS = 5


def inner_groups(inputs: ModelInputs) -> np.ndarray:
    """Group label of each row for the nested choice: its run (or fold of runs), or a block."""
    n = inputs.n_samples
    if inputs.run_index is not None and np.unique(inputs.run_index).size >= 2:
        return grouped_runs(np.asarray(inputs.run_index))
    return np.minimum(np.arange(n) * INNER_BLOCKS // max(n, 1), INNER_BLOCKS - 1)


def grouped_runs(run_index: np.ndarray) -> np.ndarray:
    """The run index itself up to ``INNER_GROUPED_ABOVE_RUNS`` runs, else ``INNER_FOLDS`` folds.

    Leave-one-run-out inside every outer fold costs runs × runs fits; with many runs
    a fold of several consecutive runs left out together is as honest (whole runs
    held out) and costs ``INNER_FOLDS`` fits per outer fold.
    """
    runs, position = np.unique(run_index, return_inverse=True)
    if runs.size <= INNER_GROUPED_ABOVE_RUNS:
        return run_index
    return position * INNER_FOLDS // runs.size


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
    """The ``RIDGE_ALPHAS`` value with the lowest pooled leave-one-group-out squared error.

    Each inner fold is solved from the group moments (:mod:`models.group_moments`):
    one eigendecomposition of the standardised training scatter gives the solution
    for every penalty at once (the one scikit-learn's ``Ridge`` finds on
    ``StandardScaler`` rises), and the held-out group's moments give its squared
    error, so the choice costs one pass over the rows however many runs there are.
    """
    alphas = np.asarray(RIDGE_ALPHAS)
    moments = GroupMoments.of(X, y, groups)
    sse = np.zeros(alphas.size)
    for k in range(moments.labels.size):
        intercepts, coefs = ridge_path(moments.without(k), alphas)
        sse += moments.group(k).squared_errors(intercepts, coefs)
    return float(alphas[int(np.argmin(sse))])


def _scales(moments: Moments, ddof: int) -> np.ndarray:
    """Column standard deviations; a constant column keeps scale 1 (as scikit-learn does)."""
    variance = np.diag(moments.xx) / (moments.count - ddof)
    scale = np.sqrt(np.maximum(variance, 0.0))
    level = np.maximum(np.abs(moments.mean[:-1]), 1.0)
    scale[scale <= 1e-10 * level] = 1.0
    return scale


def ridge_path(moments: Moments, alphas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intercepts (m,) and coefficients (p, m) of ridge on standardised columns, per penalty.

    The penalty is ``alpha × rows`` on the rises scaled by ``StandardScaler`` (ddof 0).
    """
    scale = _scales(moments, ddof=0)
    gram = moments.xx / np.outer(scale, scale)
    eigenvalues, vectors = np.linalg.eigh(gram)
    projected = vectors.T @ (moments.xy / scale)
    denominators = np.maximum(eigenvalues, 0.0)[:, None] + alphas[None, :] * moments.count
    coefs = (vectors @ (projected[:, None] / denominators)) / scale[:, None]
    return moments.mean[-1] - moments.mean[:-1] @ coefs, coefs


def pls_path(moments: Moments, components: int) -> tuple[np.ndarray, np.ndarray]:
    """Intercepts (k,) and coefficients (p, k) of PLS1 with 1 … ``components`` components.

    The kernel form of NIPALS (Dayal & MacGregor 1997) on the scatter of the rises
    scaled as ``PLSRegression(scale=True)`` scales them (ddof 1): with one target the
    first k components do not depend on how many more are extracted, so one pass
    gives every component count's solution.
    """
    scale = _scales(moments, ddof=1)
    gram = moments.xx / np.outer(scale, scale)
    cross = moments.xy / scale
    rotations = np.zeros((gram.shape[0], components))
    loadings = np.zeros_like(rotations)
    y_loadings = np.zeros(components)
    for a in range(components):
        weight = cross / np.linalg.norm(cross)
        rotation = weight - rotations[:, :a] @ (loadings[:, :a].T @ weight)
        score_ss = float(rotation @ gram @ rotation)
        loadings[:, a] = gram @ rotation / score_ss
        y_loadings[a] = float(rotation @ cross) / score_ss
        cross = cross - loadings[:, a] * y_loadings[a] * score_ss
        rotations[:, a] = rotation
    coefs = np.cumsum(rotations * y_loadings, axis=1) / scale[:, None]
    return moments.mean[-1] - moments.mean[:-1] @ coefs, coefs


def pls_components(X: np.ndarray, y: np.ndarray, groups: np.ndarray, top: int) -> int:
    """The component count (1 … ``top``) with the lowest mean leave-one-group-out MSE.

    The mean over the groups of each group's mean squared error, as scikit-learn's
    ``GridSearchCV(scoring="neg_mean_squared_error")`` scored it; the first count
    wins a tie.
    """
    moments = GroupMoments.of(X, y, groups)
    mse = np.zeros(top)
    for k in range(moments.labels.size):
        intercepts, coefs = pls_path(moments.without(k), top)
        held_out = moments.group(k)
        mse += held_out.squared_errors(intercepts, coefs) / held_out.count
    return int(np.argmin(mse)) + 1


class PlsModel(_PenalisedLinear):
    """Partial least squares on scaled rises, component count chosen by nested validation."""

    method = "pls"
    choice_key = "components"

    def _tuned(self, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> tuple[Any, float]:
        from sklearn.cross_decomposition import PLSRegression

        top = max(1, min(PLS_MAX_COMPONENTS, X.shape[1]))
        components = pls_components(X, y, groups, top)
        return PLSRegression(n_components=components, scale=True).fit(X, y), components
