"""lag-ridge's nested choice from shared per-run products equals the one refitted on rows.

The fast choice (:func:`models.estimators.lag_ridge.candidate_paths`) sums each run's
Gram products once per data set, solves every ridge from one eigendecomposition of
the sensor block and runs the lasso on a square root of the products. Here every
inner fit is instead refitted on its training rows (terms standardised on those rows,
the ridge by a linear solve per grid point, the lasso by scikit-learn's ``enet_path``
on the rows) and every held-out error summed over the held-out rows, in an outer fold
(one run left out, 12 training runs in 5 grouped inner folds). The choice (structure,
weights, penalties) must be the same, and the nested scores and the fitted values
equal to 1e-9 relative.

The coefficients themselves are held to 1e-4 of the largest only: at the smallest
ridge penalties the lagged terms are so collinear that any solve of the normal
equations, the refit's as the fast one's, is off a QR solve on the rows by as much as
they differ from each other (2e-7 at the chosen penalty 1e-6, 8e-6 at the grid's
smallest speed penalty 1e-9, measured on these runs); directions that poorly
determined do not move the fitted values. A held-out group's squared error, an
extrapolation along them, is held to 1e-7 at every grid point (1e-8 measured at the
smallest penalties) and to 1e-9 in the nested scores.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest
from sklearn.exceptions import ConvergenceWarning
from sklearn.linear_model import enet_path

from models.base import ModelInputs
from models.data.dataset import load_runs
from models.data.features import Prepared, prepare
from models.estimators.lag_ridge import candidate_paths, lag_terms, term_names
from models.estimators.lag_structures import (
    FITTED,
    LASSO,
    LASSO_PENALTIES,
    PENALTIES,
    SPEED_GROUP,
    STRUCTURES,
    CandidatePaths,
    Choice,
    choose,
)
from models.estimators.ridge_pls import inner_groups
from tests.test_lag_ridge import synthetic_csv

RTOL = 1e-9
COEFFICIENT_RTOL = 1e-4
HELD_OUT_RTOL = 1e-7
RUNS = 13  # one held out, 12 training runs: above the threshold of grouped inner folds


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Prepared:
    path = tmp_path_factory.mktemp("paths") / "runs.csv"
    return prepare(load_runs(synthetic_csv(path, runs=RUNS, seed=11)))


def one_recording(inputs: ModelInputs) -> ModelInputs:
    """The same runs as one continuous recording: the lags carry from run to run."""
    time_s = inputs.time_s + 8 * 3600.0 * inputs.run_index
    return dataclasses.replace(
        inputs, time_s=time_s, recording=np.zeros(inputs.n_samples, dtype=int)
    )


class RowGroups:
    """The groups of training rows, every product taken over the rows themselves."""

    def __init__(self, terms: np.ndarray, y: np.ndarray, labels: np.ndarray) -> None:
        self.terms, self.y, self.row_labels = terms, y, labels
        self.labels = list(dict.fromkeys(labels[labels >= 0].tolist()))

    def rows(self, members) -> np.ndarray:
        return np.isin(self.row_labels, [self.labels[m] for m in members])

    def sse(self, member: int, beta: np.ndarray) -> float:
        rows = self.rows([member])
        return float(np.sum((self.y[rows] - beta[0] - self.terms[rows] @ beta[1:]) ** 2))

    def total(self, members) -> tuple[np.ndarray, np.ndarray]:
        rows = self.rows(members)
        z = np.column_stack([np.ones(int(rows.sum())), self.terms[rows]])
        return z.T @ z, z.T @ self.y[rows]


class RefittedPaths(CandidatePaths):
    """A candidate whose every fit is refitted on the rows of its training groups."""

    def __init__(self, structure, terms, y, labels, n_sensors, names) -> None:
        super().__init__(structure, terms, y, labels, n_sensors, names)
        self.grams = RowGroups(terms, y, labels)

    def path(self, members: frozenset[int]) -> list[np.ndarray]:
        cached = self._paths.get(members)
        if cached is None:
            cached = self._refit(members)
            self._paths[members] = cached
        return cached

    def _refit(self, members: frozenset[int]) -> list[np.ndarray]:
        rows = self.grams.rows(members)
        z, y = self.terms[rows], self.y[rows]
        fitted = self.structure.intercept == FITTED
        scale = z.std(axis=0)
        scale[scale <= 1e-12 * max(float(scale.max()), 1.0)] = 1.0
        mean = z.mean(axis=0) if fitted else np.zeros(z.shape[1])
        y_mean = float(y.mean()) if fitted else 0.0
        zs, yc = (z - mean) / scale, y - y_mean
        if self.structure.estimator == LASSO:
            sigma = float(np.sqrt(np.mean(yc**2)))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                _, coefs, _ = enet_path(
                    zs, yc, l1_ratio=1.0, alphas=sigma * np.asarray(LASSO_PENALTIES),
                    max_iter=5000, precompute=True,
                )  # fmt: skip
            solutions = list(coefs.T)
        else:
            speed = self.groups == SPEED_GROUP
            solutions = [
                np.linalg.solve(
                    zs.T @ zs + rows.sum() * np.diag(np.where(speed, p * r, p)), zs.T @ yc
                )
                for r in self._ratios
                for p in PENALTIES
            ]
        return [np.r_[y_mean - mean @ (u / scale), u / scale] for u in solutions]


def refitted(inputs: ModelInputs, y: np.ndarray, labels: np.ndarray) -> Choice:
    sensors = inputs.sensors
    return choose(
        [
            RefittedPaths(
                s,
                lag_terms(inputs, sensors, s.lag_taus_s, s.speed_powers),
                y,
                labels,
                len(sensors),
                term_names(sensors, s.lag_taus_s, s.speed_powers),
            )
            for s in STRUCTURES
        ]
    )


def outer_fold_labels(inputs: ModelInputs, held_out_run: int) -> np.ndarray:
    train = inputs.run_index != held_out_run
    labels = np.full(inputs.n_samples, -1)
    labels[train] = inner_groups(inputs.take(train))
    return labels


def assert_same_choice(fast: Choice, slow: Choice, inputs: ModelInputs) -> None:
    assert fast.structure == slow.structure
    assert fast.weights == slow.weights
    assert fast.penalties == slow.penalties
    assert fast.inner_rmse_um.keys() == slow.inner_rmse_um.keys()
    for name, rmse in slow.inner_rmse_um.items():
        assert fast.inner_rmse_um[name] == pytest.approx(rmse, rel=RTOL)
    terms = lag_terms(
        inputs, inputs.sensors, slow.structure.lag_taus_s, slow.structure.speed_powers
    )
    fitted_slow = slow.beta[0] + terms @ slow.beta[1:]
    fitted_fast = fast.beta[0] + terms @ fast.beta[1:]
    assert_close(fitted_fast, fitted_slow, RTOL)
    assert_close(fast.beta, slow.beta, COEFFICIENT_RTOL)
    np.testing.assert_allclose(fast.mean, slow.mean, rtol=RTOL)
    np.testing.assert_allclose(fast.scale, slow.scale, rtol=RTOL)


def assert_close(got: np.ndarray, want: np.ndarray, rtol: float) -> None:
    """Equal to ``rtol`` relative to the largest of ``want`` (a zeroed lasso term is 0)."""
    np.testing.assert_allclose(got, want, rtol=0, atol=rtol * np.abs(want).max())


@pytest.mark.parametrize("continuous", [False, True], ids=["run-recordings", "one-recording"])
def test_the_nested_choice_from_run_products_equals_refits_on_rows(
    runs: Prepared, continuous: bool
) -> None:
    inputs = one_recording(runs.inputs) if continuous else runs.inputs
    y = runs.error_um
    labels = outer_fold_labels(inputs, held_out_run=4)
    assert len(set(labels[labels >= 0].tolist())) == 5  # grouped inner folds
    fast = choose(candidate_paths(inputs, inputs.sensors, STRUCTURES, y, labels))
    slow = refitted(inputs, y, labels)
    assert_same_choice(fast, slow, inputs)


def test_every_grid_point_of_every_structure_equals_its_refit(runs: Prepared) -> None:
    """Each structure's fits on three of the five inner groups (two left out, as in the
    inner loop) at every grid point, and their held-out squared errors."""
    inputs, y = runs.inputs, runs.error_um
    labels = outer_fold_labels(inputs, held_out_run=0)
    fast = candidate_paths(inputs, inputs.sensors, STRUCTURES, y, labels)
    members = frozenset({0, 2, 3})
    for candidate in fast:
        slow = RefittedPaths(
            candidate.structure,
            lag_terms(inputs, inputs.sensors, *_lags(candidate)),
            y,
            labels,
            len(inputs.sensors),
            candidate.names,
        )
        rows = slow.grams.rows(members)
        for got, want in zip(candidate.path(members), slow.path(members), strict=True):
            assert_close(
                slow.terms[rows] @ got[1:] + got[0], slow.terms[rows] @ want[1:] + want[0], RTOL
            )
            assert_close(got, want, COEFFICIENT_RTOL)
        for held in (1, 4):
            got_sse = [candidate.grams.sse(held, b) for b in candidate.path(members)]
            want_sse = [slow.grams.sse(held, b) for b in slow.path(members)]
            np.testing.assert_allclose(got_sse, want_sse, rtol=HELD_OUT_RTOL)


def _lags(candidate: CandidatePaths) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return candidate.structure.lag_taus_s, candidate.structure.speed_powers


def test_a_second_data_set_does_not_reuse_the_first_ones_products(
    runs: Prepared, tmp_path: Path
) -> None:
    """The products are kept per data set by content: other runs, other products."""
    other = prepare(load_runs(synthetic_csv(tmp_path / "other.csv", runs=RUNS, seed=12)))
    for prepared in (runs, other, runs):
        inputs, y = prepared.inputs, prepared.error_um
        labels = outer_fold_labels(inputs, held_out_run=7)
        fast = choose(candidate_paths(inputs, inputs.sensors, STRUCTURES, y, labels))
        assert_same_choice(fast, refitted(inputs, y, labels), inputs)
