"""lag-ridge's penalised fits from Gram products alone, whatever the number of rows.

- :class:`TwoGroupRidge`: the ridge with one penalty λ on the sensor terms and r·λ on
  the speed terms, at every λ and r, from one eigendecomposition of the sensor block
  (the speed terms, a few dozen, enter through a Schur complement solved per point).
  One eigendecomposition of the whole standardised Gram matrix per ratio r gives the
  same solutions; the sensor block alone is smaller and serves every r, and the
  one-penalty ridge is its r = 1.
- :func:`square_root_rows`: p + 1 rows ``[A b]`` with ``[A b]ᵀ[A b]`` the centred,
  standardised ``[Z y]ᵀ[Z y]`` of the training rows. A lasso path on them is the lasso
  path on the rows (its L1 penalty rescaled to their count), so the lasso needs no
  pass over the rows either.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def centred_products(
    gram: np.ndarray, cross: np.ndarray, yy: float, mean: np.ndarray, y_mean: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Σ(z − m)(z − m)ᵀ, Σ(z − m)(y − ȳ), Σ(y − ȳ)² from the products of [1, Z] and y.

    ``mean`` and ``y_mean`` are what the fit removes: the training means with a fitted
    intercept, zeros when it is held at 0 µm.
    """
    n = gram[0, 0]
    sums, sum_y = gram[0, 1:], cross[0]
    zz = gram[1:, 1:] - np.outer(mean, sums) - np.outer(sums, mean) + n * np.outer(mean, mean)
    zy = cross[1:] - mean * sum_y - y_mean * sums + n * mean * y_mean
    return zz, zy, float(yy - 2.0 * y_mean * sum_y + n * y_mean**2)


class TwoGroupRidge:
    """Solutions of (C + n·diag(λ on sensors, r·λ on speed)) u = c on standardised terms.

    C and c are the centred, standardised products of the training rows; the
    coefficients in the terms' own units are u / scale.
    """

    def __init__(self, zz: np.ndarray, zy: np.ndarray, n: float, speed: np.ndarray) -> None:
        """``zz``, ``zy``: standardised centred products; ``speed``: mask of the speed terms."""
        self.n = n
        self.sensor, self.speed = ~speed, speed
        eigenvalues, vectors = np.linalg.eigh(zz[np.ix_(self.sensor, self.sensor)])
        self.eigenvalues, self.vectors = eigenvalues, vectors
        self.coupling = zz[np.ix_(speed, self.sensor)] @ vectors  # C_ps Q
        self.projected = vectors.T @ zy[self.sensor]  # Qᵀ c_s
        self.speed_block = zz[np.ix_(speed, speed)]
        self.speed_cross = zy[speed]
        self._at: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _reduced(self, penalty: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(d, C_ps A⁻¹ C_sp, C_ps A⁻¹ c_s) with A = C_ss + nλ, d = 1/eig(A), kept per λ."""
        kept = self._at.get(penalty)
        if kept is None:
            d = 1.0 / np.maximum(self.eigenvalues + self.n * penalty, 1e-300)
            kept = (d, (self.coupling * d) @ self.coupling.T, self.coupling @ (d * self.projected))
            self._at[penalty] = kept
        return kept

    def solve(self, penalty: float, ratio: float) -> np.ndarray:
        """u at sensor penalty λ and speed penalty ratio·λ (standardised coefficients)."""
        d, schur, shift = self._reduced(penalty)
        u = np.empty(self.sensor.size)
        rest = self.projected
        if self.speed.any():
            system = self.speed_block - schur
            system[np.diag_indices_from(system)] += self.n * penalty * ratio
            u_speed = np.linalg.solve(system, self.speed_cross - shift)
            u[self.speed] = u_speed
            rest = self.projected - self.coupling.T @ u_speed
        u[self.sensor] = self.vectors @ (d * rest)
        return u


def ridge_solutions(
    solver: TwoGroupRidge,
    ratios: Sequence[float],
    penalties: Sequence[float],
    mean: np.ndarray,
    scale: np.ndarray,
    y_mean: float,
) -> list[np.ndarray]:
    """[intercept, coefficients] for every ratio and, within it, every penalty.

    The speed terms' systems of every grid point are solved in one batched call (the
    same LAPACK solve per point as :meth:`TwoGroupRidge.solve`, without a Python call
    and its checks each: a fold's 105 points cost about a tenth as much)."""
    grid = [(penalty, ratio) for ratio in ratios for penalty in penalties]
    if not solver.speed.any():
        solutions = [solver.solve(penalty, ratio) for penalty, ratio in grid]
    else:
        solutions = _batched_solutions(solver, grid)
    path = []
    for u in solutions:
        b = u / scale
        path.append(np.r_[y_mean - mean @ b, b])
    return path


def _batched_solutions(solver: TwoGroupRidge, grid: list[tuple[float, float]]) -> list[np.ndarray]:
    """:meth:`TwoGroupRidge.solve` at every (penalty, ratio) of ``grid``, the speed systems
    stacked into one solve."""
    reduced = [solver._reduced(penalty) for penalty, _ in grid]
    k = int(solver.speed.sum())
    systems = np.empty((len(grid), k, k))
    rhs = np.empty((len(grid), k, 1))
    diagonal = np.arange(k)
    for i, ((penalty, ratio), (_, schur, shift)) in enumerate(zip(grid, reduced, strict=True)):
        np.subtract(solver.speed_block, schur, out=systems[i])
        systems[i, diagonal, diagonal] += solver.n * penalty * ratio
        rhs[i, :, 0] = solver.speed_cross - shift
    speed_parts = np.linalg.solve(systems, rhs)[:, :, 0]
    solutions = []
    for (d, _, _), u_speed in zip(reduced, speed_parts, strict=True):
        u = np.empty(solver.sensor.size)
        u[solver.speed] = u_speed
        u[solver.sensor] = solver.vectors @ (d * (solver.projected - solver.coupling.T @ u_speed))
        solutions.append(u)
    return solutions


def square_root_rows(zz: np.ndarray, zy: np.ndarray, yy: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, b), p + 1 rows whose products AᵀA, Aᵀb, bᵀb are ``zz``, ``zy``, ``yy``
    (a symmetric square root of the products; rounding below zero is clipped)."""
    p = zz.shape[0]
    products = np.empty((p + 1, p + 1))
    products[:p, :p], products[:p, p], products[p, :p], products[p, p] = zz, zy, zy, yy
    eigenvalues, vectors = np.linalg.eigh(products)
    root = np.sqrt(np.maximum(eigenvalues, 0.0))[:, None] * vectors.T
    return np.asfortranarray(root[:, :p]), np.ascontiguousarray(root[:, p])
