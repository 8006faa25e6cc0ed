"""Correlation-matrix PCA (paper 000, §2.2): recovery of a known structure, the
cumulative-contribution rule, the sign convention and scale invariance."""

from __future__ import annotations

import numpy as np
import pytest

from models.estimators.parts.pca import ConstantVariableError, correlation_pca, n_components_for

# A correlation matrix with chosen eigenvalues: R = Q diag(λ) Qᵀ. Every entry of Q
# is ±1/2, so diag(R)_i = Σ λ_k / 4 = 1 because Σλ = p = 4.
EIGENVALUES = np.array([2.5, 1.0, 0.4, 0.1])
Q = 0.5 * np.array(
    [
        [1.0, 1.0, 1.0, 1.0],
        [1.0, -1.0, 1.0, -1.0],
        [1.0, 1.0, -1.0, -1.0],
        [1.0, -1.0, -1.0, 1.0],
    ]
)
R = Q @ np.diag(EIGENVALUES) @ Q.T
SDS = np.array([0.5, 3.0, 40.0, 0.01])
MEANS = np.array([20.0, -5.0, 1000.0, 0.3])

# Paper 000, §2.2: eigenvalues of the 9-sensor correlation matrix.
PAPER_EIGENVALUES = np.array(
    [7.5965, 1.2036, 0.0993, 0.0578, 0.0273, 0.0113, 0.0025, 0.0010, 0.0006]
)


def _sample(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.multivariate_normal(np.zeros(4), R, size=n)
    return MEANS + z * SDS


@pytest.fixture(scope="module")
def large() -> np.ndarray:
    return _sample(200_000)


def test_known_correlation_matrix_is_valid() -> None:
    np.testing.assert_allclose(np.diag(R), 1.0)
    np.testing.assert_allclose(Q.T @ Q, np.eye(4), atol=1e-15)


def test_recovers_eigenvalues_and_eigenvectors(large: np.ndarray) -> None:
    result = correlation_pca(large)
    np.testing.assert_allclose(result.eigenvalues, EIGENVALUES, rtol=0.02)
    assert np.all(np.diff(result.eigenvalues) < 0)
    for i in range(4):
        assert abs(result.components[:, i] @ Q[:, i]) > 0.999
    np.testing.assert_allclose(result.components.T @ result.components, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(result.contribution, EIGENVALUES / 4, atol=0.01)
    np.testing.assert_allclose(result.mean, MEANS, atol=0.01 * SDS.max())
    np.testing.assert_allclose(result.scale, SDS, rtol=0.01)


def test_cumulative_rule_on_known_structure(large: np.ndarray) -> None:
    # exact cumulative: 0.625, 0.875, 0.975, 1.0
    exact = np.cumsum(EIGENVALUES) / EIGENVALUES.sum()
    assert [n_components_for(exact, t) for t in (0.6, 0.8, 0.85, 0.9, 0.98)] == [1, 2, 2, 3, 4]
    assert correlation_pca(large).n_kept == 2  # 85 % default: 3.5 / 4 = 87.5 %
    assert correlation_pca(large, threshold=0.8).n_kept == 2
    assert correlation_pca(large, threshold=0.6).n_kept == 1
    assert correlation_pca(large, threshold=0.9).n_kept == 3
    assert correlation_pca(large, threshold=1.0).n_kept == 4


def test_n_components_for_exact_cases() -> None:
    assert n_components_for(np.array([0.5, 0.85, 1.0]), 0.85) == 2  # equal counts
    assert n_components_for(np.cumsum([0.5, 0.35, 0.15]), 0.85) == 2  # equal up to rounding
    assert n_components_for(np.array([0.84, 0.86, 1.0]), 0.85) == 2
    assert n_components_for(np.array([0.86, 0.9, 1.0]), 0.85) == 1
    assert n_components_for(np.array([0.5, 0.9, 1.0]), 0.5) == 1
    assert n_components_for(np.array([0.6, 0.9, 1.0]), 1.0) == 3
    for bad in (0.0, -0.1, 1.01):
        with pytest.raises(ValueError, match="threshold"):
            n_components_for(np.array([0.5, 1.0]), bad)


def test_paper_eigenvalues() -> None:
    cumulative = np.cumsum(PAPER_EIGENVALUES) / PAPER_EIGENVALUES.sum()
    assert round(100 * cumulative[0], 2) == 84.41
    assert round(100 * cumulative[1], 2) == 97.78
    assert n_components_for(cumulative, 0.85) == 2
    assert n_components_for(cumulative, 0.84) == 1


def test_sign_convention_largest_loading_positive(large: np.ndarray) -> None:
    for seed in range(5):
        result = correlation_pca(_sample(500, seed=seed))
        for i in range(4):
            column = result.components[:, i]
            assert column[np.argmax(np.abs(column))] > 0


def test_common_level_gives_all_positive_first_loadings() -> None:
    # Like the paper's x1: every sensor follows one overall level.
    rng = np.random.default_rng(3)
    level = rng.uniform(0, 20, size=400)
    values = level[:, None] * np.array([1.0, 0.8, 1.5, 0.6, 1.2]) + rng.normal(0, 0.3, (400, 5))
    result = correlation_pca(values)
    assert result.n_kept == 1
    assert np.all(result.components[:, 0] > 0)
    np.testing.assert_allclose(result.components[:, 0], 1 / np.sqrt(5), atol=0.01)


def test_scale_and_shift_invariance() -> None:
    values = _sample(2000, seed=1)
    changed = values.copy()
    changed[:, 1] *= 1000.0
    changed[:, 3] += 250.0
    a = correlation_pca(values)
    b = correlation_pca(changed)
    np.testing.assert_allclose(b.eigenvalues, a.eigenvalues, rtol=1e-10)
    np.testing.assert_allclose(b.components, a.components, atol=1e-10)
    assert b.n_kept == a.n_kept
    np.testing.assert_allclose(b.scores(changed), a.scores(values), atol=1e-9)


def test_scores_are_uncorrelated_with_eigenvalue_variances() -> None:
    values = _sample(3000, seed=2)
    result = correlation_pca(values)
    scores = result.scores(values, n=4)
    assert scores.shape == (3000, 4)
    np.testing.assert_allclose(scores.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(
        np.cov(scores, rowvar=False), np.diag(result.eigenvalues), atol=1e-10
    )
    assert result.scores(values).shape == (3000, result.n_kept)
    with pytest.raises(ValueError):
        result.scores(values, n=5)
    with pytest.raises(ValueError):
        result.scores(values[:, :3])


def test_invalid_inputs() -> None:
    values = _sample(50)
    values[:, 2] = 7.0
    with pytest.raises(ConstantVariableError, match="column 2") as info:
        correlation_pca(values)
    assert info.value.column == 2
    assert isinstance(info.value, ValueError)
    with pytest.raises(ValueError, match="2 rows"):
        correlation_pca(_sample(1))
    nan = _sample(10)
    nan[3, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        correlation_pca(nan)
    with pytest.raises(ValueError, match="threshold"):
        correlation_pca(_sample(10), threshold=0.0)
