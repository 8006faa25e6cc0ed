"""Principal component analysis on the correlation matrix (paper 000, §2.2).

Wang & Wu (2026) reduce many collinear spindle temperatures to a few
uncorrelated components before regression:

1. z-score every variable: z_ij = (t_ij − mean_j) / s_j, s_j the sample SD (ddof = 1);
2. correlation matrix R = Zᵀ Z / (n − 1) (p × p);
3. eigen-decompose R, eigenvalues λ_1 ≥ λ_2 ≥ … ≥ λ_p with unit eigenvectors a_i;
4. contribution λ_i / Σλ, cumulative Σ_{i≤m} λ_i / Σλ; keep the smallest m whose
   cumulative contribution reaches the threshold (85 % in the paper: 9 sensors,
   λ = 7.5965, 1.2036, … → 84.41 %, 97.78 % → m = 2);
5. component scores x_i = Z a_i.

Working on R rather than the covariance matrix makes the result independent of
each variable's unit and spread (scale invariance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Slack when comparing a cumulative contribution with the threshold, so that a
#: cumulative equal to the threshold up to rounding (0.5 + 0.35 vs 0.85) counts.
CUMULATIVE_TOLERANCE = 1e-12


class ConstantVariableError(ValueError):
    """A variable has zero spread, so it cannot be z-scored. ``column`` is its index."""

    def __init__(self, column: int) -> None:
        super().__init__(f"column {column} is constant (sample SD 0): it cannot be z-scored")
        self.column = column


@dataclass(frozen=True)
class PcaResult:
    """A fitted correlation-matrix PCA.

    Attributes:
        mean: (p,) per-variable mean used to z-score.
        scale: (p,) per-variable sample SD (ddof = 1) used to z-score.
        eigenvalues: (p,) all eigenvalues of the correlation matrix, descending.
        components: (p, p) columns are the unit eigenvectors (loadings) in the
            same order; each column's sign is fixed so its largest-|loading|
            entry is positive. A result rebuilt from a store may hold only the
            first ``n_kept`` columns, (p, n_kept).
        contribution: (p,) λ_i / Σλ.
        cumulative: (p,) running sum of ``contribution``.
        n_kept: number of components kept (see :func:`n_components_for`).
        threshold: cumulative contribution the kept components reach.
    """

    mean: np.ndarray
    scale: np.ndarray
    eigenvalues: np.ndarray
    components: np.ndarray
    contribution: np.ndarray
    cumulative: np.ndarray
    n_kept: int
    threshold: float

    def scores(self, values: np.ndarray, n: int | None = None) -> np.ndarray:
        """(rows, n) component scores x_i = z a_i, z = (values − mean) / scale.

        ``n`` defaults to ``n_kept``; it may not exceed the stored columns.
        """
        n = self.n_kept if n is None else n
        if not 1 <= n <= self.components.shape[1]:
            raise ValueError(f"n must be in 1..{self.components.shape[1]}, got {n}")
        x = np.asarray(values, dtype=float)
        if x.ndim != 2 or x.shape[1] != self.mean.shape[0]:
            raise ValueError(f"values must be (rows, {self.mean.shape[0]}), got shape {x.shape}")
        z = (x - self.mean) / self.scale
        # A contiguous copy, so a full and a truncated (stored) basis give the same bits.
        basis = np.ascontiguousarray(self.components[:, :n])
        return z @ basis


def n_components_for(cumulative: np.ndarray, threshold: float) -> int:
    """Smallest m with cumulative[m − 1] ≥ threshold (paper 000, §2.2).

    A cumulative equal to the threshold reaches it (within ``CUMULATIVE_TOLERANCE``
    for rounding). If none reaches it (only possible through rounding with
    threshold 1), all components are kept.
    """
    _check_threshold(threshold)
    cum = np.asarray(cumulative, dtype=float)
    if cum.ndim != 1 or cum.size == 0:
        raise ValueError(f"cumulative must be a non-empty 1-D array, got shape {cum.shape}")
    reached = np.flatnonzero(cum >= threshold - CUMULATIVE_TOLERANCE)
    return int(reached[0]) + 1 if reached.size else int(cum.size)


def correlation_pca(values: np.ndarray, threshold: float = 0.85) -> PcaResult:
    """PCA of ``values`` (n, p) on its correlation matrix; see the module docstring.

    Raises:
        ValueError: fewer than 2 rows, non-finite values, threshold outside (0, 1].
        ConstantVariableError: a column with sample SD 0 (its index in ``column``).
    """
    _check_threshold(threshold)
    x = np.asarray(values, dtype=float)
    if x.ndim != 2 or x.shape[1] < 1:
        raise ValueError(f"values must be (n, p) with p ≥ 1, got shape {x.shape}")
    if x.shape[0] < 2:
        raise ValueError(f"PCA needs at least 2 rows, got {x.shape[0]}")
    if not np.all(np.isfinite(x)):
        raise ValueError("PCA needs finite values (found NaN or inf)")

    mean = x.mean(axis=0)
    scale = x.std(axis=0, ddof=1)
    for j, s in enumerate(scale):
        if s == 0:
            raise ConstantVariableError(j)
    z = (x - mean) / scale
    corr = z.T @ z / (x.shape[0] - 1)

    eigenvalues, vectors = np.linalg.eigh(corr)  # ascending
    order = np.argsort(eigenvalues)[::-1]
    # R is positive semi-definite: a tiny negative eigenvalue is rounding.
    eigenvalues = np.clip(eigenvalues[order], 0.0, None)
    vectors = vectors[:, order]
    largest = np.argmax(np.abs(vectors), axis=0)
    signs = np.where(vectors[largest, np.arange(vectors.shape[1])] < 0, -1.0, 1.0)
    vectors = vectors * signs

    contribution = eigenvalues / eigenvalues.sum()
    cumulative = np.cumsum(contribution)
    return PcaResult(
        mean=mean,
        scale=scale,
        eigenvalues=eigenvalues,
        components=vectors,
        contribution=contribution,
        cumulative=cumulative,
        n_kept=n_components_for(cumulative, threshold),
        threshold=float(threshold),
    )


def _check_threshold(threshold: float) -> None:
    if not 0.0 < threshold <= 1.0:
        raise ValueError(f"threshold must be in (0, 1], got {threshold}")
