"""Full quadratic response surface, as MATLAB ``rstool`` model ``'quadratic'``.

Paper 000 (Wang & Wu 2026, §3.1) fits, for inputs x1, x2, x3,

    y = b0 + b1 x1 + b2 x2 + b3 x3 + b12 x1 x2 + b13 x1 x3 + b23 x2 x3
           + b11 x1² + b22 x2² + b33 x3²

— for k inputs 1 + k + k(k − 1)/2 + k terms (10 for k = 3), in rstool's order:
constant, linear terms, interactions x_i x_j (i < j, lexicographic), squares.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations

import numpy as np


def n_quadratic_terms(k: int) -> int:
    """Number of terms of the full quadratic in k inputs: 1 + k + k(k − 1)/2 + k."""
    return 1 + k + k * (k - 1) // 2 + k


def quadratic_terms(names: Sequence[str]) -> list[str]:
    """Term names in rstool order: "1", x_i, x_i*x_j (i < j), x_i^2.

    ``("x1", "x2", "x3")`` → ``["1", "x1", "x2", "x3", "x1*x2", "x1*x3", "x2*x3",
    "x1^2", "x2^2", "x3^2"]``.
    """
    names = list(names)
    if not names:
        raise ValueError("need at least one input name")
    interactions = [f"{a}*{b}" for a, b in combinations(names, 2)]
    return ["1", *names, *interactions, *(f"{a}^2" for a in names)]


def quadratic_design(X: np.ndarray) -> np.ndarray:
    """Design matrix (n, k) → (n, 1 + k + k(k − 1)/2 + k), columns in the order of
    :func:`quadratic_terms`."""
    x = np.asarray(X, dtype=float)
    if x.ndim != 2 or x.shape[1] < 1:
        raise ValueError(f"X must be (n, k) with k ≥ 1, got shape {x.shape}")
    k = x.shape[1]
    columns = [np.ones(x.shape[0]), *(x[:, i] for i in range(k))]
    columns += [x[:, i] * x[:, j] for i, j in combinations(range(k), 2)]
    columns += [x[:, i] ** 2 for i in range(k)]
    return np.column_stack(columns)


def fit_least_squares(design: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Coefficients b minimising ‖design · b − y‖², by ``numpy.linalg.lstsq`` (rcond=None).

    lstsq works through the SVD, so a rank-deficient design (e.g. runs at one
    speed only, where 1, x3 and x3² are collinear) yields the minimum-norm
    solution rather than an error; callers that care check the rank.
    """
    a = np.asarray(design, dtype=float)
    b = np.asarray(y, dtype=float)
    if a.ndim != 2 or b.shape != (a.shape[0],):
        raise ValueError(f"need design (n, q) and y (n,), got {a.shape} and {b.shape}")
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    return coef
