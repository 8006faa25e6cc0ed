"""The fast nested choices of ridge and PLS equal the refitting ones they replaced.

Ridge's penalty and PLS's component count are chosen from per-group moments
(models/group_moments.py) instead of one refit per inner fold; these tests hold
the fast paths to the slow definitions (an SVD per held-out group for ridge,
scikit-learn's ``PLSRegression`` in a ``GridSearchCV`` for PLS) to 1e-9 relative,
and the grouping of inner folds to plain leave-one-run-out up to its threshold.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter
from sklearn.cross_decomposition import PLSRegression
from sklearn.linear_model import Ridge
from sklearn.model_selection import GridSearchCV, LeaveOneGroupOut
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from models.base import ModelInputs
from models.estimators.ridge_pls import (
    INNER_FOLDS,
    INNER_GROUPED_ABOVE_RUNS,
    RIDGE_ALPHAS,
    inner_groups,
    pls_components,
    pls_path,
    ridge_path,
    ridge_penalty,
)
from models.group_moments import GroupMoments

RTOL = 1e-9


def recording(runs: int, rows_per_run: int = 300, sensors: int = 12, seed: int = 0):
    """Collinear rises (first-order lags of one speed-driven heat input) and an error, per run."""
    rng = np.random.default_rng(seed)
    n = runs * rows_per_run
    drive = np.repeat(rng.choice([0.0, 0.3, 0.6, 1.0], size=n // 20 + 1), 20)[:n]
    rises = []
    for i in range(sensors):
        a = np.exp(-1.0 / (15.0 + 10.0 * i))
        rises.append(12.0 * lfilter([1 - a], [1, -a], drive) + rng.normal(0, 0.05, n))
    X = np.column_stack(rises) + 20.0  # absolute levels: the moments must not cancel them
    y = 3.0 * X[:, 0] - 1.5 * X[:, 5] + 0.4 * X[:, -1] + rng.normal(0, 0.3, n)
    groups = np.repeat(np.arange(runs), rows_per_run)
    return X, y, groups


def ridge_sse_by_refits(X, y, groups):
    """Pooled held-out squared error per penalty, one scikit-learn fit per group and penalty."""
    sse = np.zeros(len(RIDGE_ALPHAS))
    for group in np.unique(groups):
        test = groups == group
        n_train = int((~test).sum())
        for i, alpha in enumerate(RIDGE_ALPHAS):
            model = make_pipeline(StandardScaler(), Ridge(alpha=alpha * n_train))
            model.fit(X[~test], y[~test])
            sse[i] += np.sum((y[test] - model.predict(X[test])) ** 2)
    return sse


def ridge_sse_by_moments(X, y, groups):
    moments = GroupMoments.of(X, y, groups)
    sse = np.zeros(len(RIDGE_ALPHAS))
    for k in range(moments.labels.size):
        sse += moments.group(k).squared_errors(
            *ridge_path(moments.without(k), np.asarray(RIDGE_ALPHAS))
        )
    return sse


@pytest.mark.parametrize("runs", [2, 6, 14])
def test_ridge_inner_errors_equal_refits(runs):
    X, y, groups = recording(runs, seed=runs)
    slow = ridge_sse_by_refits(X, y, groups)
    fast = ridge_sse_by_moments(X, y, groups)
    np.testing.assert_allclose(fast, slow, rtol=RTOL)
    assert ridge_penalty(X, y, groups) == RIDGE_ALPHAS[int(np.argmin(slow))]


def test_ridge_path_equals_sklearn_coefficients():
    X, y, groups = recording(5)
    moments = GroupMoments.of(X, y, np.zeros_like(groups)).group(0)
    intercepts, coefs = ridge_path(moments, np.asarray(RIDGE_ALPHAS))
    for i, alpha in enumerate(RIDGE_ALPHAS):
        model = make_pipeline(StandardScaler(), Ridge(alpha=alpha * X.shape[0])).fit(X, y)
        scaler, ridge = model
        coef = ridge.coef_ / scaler.scale_
        np.testing.assert_allclose(coefs[:, i], coef, rtol=RTOL, atol=1e-12 * np.abs(coef).max())
        np.testing.assert_allclose(intercepts[i], model.predict(np.zeros((1, X.shape[1])))[0])


def test_pls_path_equals_sklearn_per_component_count():
    X, y, _ = recording(4)
    moments = GroupMoments.of(X, y, np.zeros(X.shape[0])).group(0)
    intercepts, coefs = pls_path(moments, 8)
    probe = np.vstack([np.zeros(X.shape[1]), np.eye(X.shape[1])])
    for k in range(1, 9):
        values = np.ravel(PLSRegression(n_components=k, scale=True).fit(X, y).predict(probe))
        np.testing.assert_allclose(intercepts[k - 1], values[0], rtol=RTOL)
        coef = values[1:] - values[0]
        np.testing.assert_allclose(coefs[:, k - 1], coef, rtol=RTOL, atol=RTOL * np.abs(coef).max())


@pytest.mark.parametrize("runs", [3, 6, 14])
def test_pls_component_choice_equals_grid_search(runs):
    X, y, groups = recording(runs, seed=10 + runs)
    search = GridSearchCV(
        PLSRegression(scale=True),
        {"n_components": list(range(1, 9))},
        cv=LeaveOneGroupOut(),
        scoring="neg_mean_squared_error",
    ).fit(X, y, groups=groups)
    moments = GroupMoments.of(X, y, groups)
    mse = np.zeros(8)
    for k in range(moments.labels.size):
        held_out = moments.group(k)
        mse += held_out.squared_errors(*pls_path(moments.without(k), 8)) / held_out.count
    np.testing.assert_allclose(-mse / runs, search.cv_results_["mean_test_score"], rtol=RTOL)
    assert pls_components(X, y, groups, 8) == search.best_params_["n_components"]


def inputs_of(runs: int, rows_per_run: int = 4) -> ModelInputs:
    n = runs * rows_per_run
    return ModelInputs(
        rise_C=np.zeros((n, 1)),
        sensors=("T1",),
        speed_rpm=np.zeros(n),
        run_index=np.repeat(np.arange(runs), rows_per_run),
    )


def test_inner_groups_are_the_runs_up_to_the_threshold():
    for runs in range(2, INNER_GROUPED_ABOVE_RUNS + 1):
        inputs = inputs_of(runs)
        np.testing.assert_array_equal(inner_groups(inputs), inputs.run_index)


def test_inner_groups_above_the_threshold_are_folds_of_whole_runs():
    inputs = inputs_of(INNER_GROUPED_ABOVE_RUNS + 7)
    labels = inner_groups(inputs)
    assert np.unique(labels).size == INNER_FOLDS
    for run in np.unique(inputs.run_index):
        assert np.unique(labels[inputs.run_index == run]).size == 1  # a run is never split


def test_parallel_held_out_folds_equal_serial(tmp_path, monkeypatch):
    """From PARALLEL_FROM_FOLDS folds on, worker processes fit the folds: same predictions."""
    import pandas as pd

    from models.data.dataset import load_runs
    from models.data.features import prepare
    from models.estimators.registry import make_model
    from models.fit import crossval

    runs = crossval.PARALLEL_FROM_FOLDS
    X, y, groups = recording(runs, rows_per_run=60, sensors=6, seed=3)
    frame = pd.DataFrame(X - 20.0, columns=[f"T{i + 1}" for i in range(X.shape[1])])
    frame.insert(0, "speed_rpm", 3000.0)
    frame.insert(0, "time_s", np.tile(np.arange(60) * 40.0, runs))
    frame.insert(0, "run", [f"r{g:02d}" for g in groups])
    frame["error_um"] = y
    path = tmp_path / "runs.csv"
    frame.to_csv(path, index=False)
    prepared = prepare(load_runs(path, target="error_um"))

    def factory():
        return make_model("ridge")

    parallel = crossval.cross_validate(factory, prepared)
    monkeypatch.setattr(crossval, "PARALLEL_FROM_FOLDS", runs + 1)
    serial = crossval.cross_validate(factory, prepared)
    assert parallel.folds == serial.folds and len(parallel.folds) == runs
    np.testing.assert_allclose(parallel.predicted_um, serial.predicted_um, rtol=RTOL, atol=1e-12)
