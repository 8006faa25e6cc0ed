"""Per-group means and scatter matrices of a design, for nested choices without refits.

Leave-one-group-out inside a fit used to refit on every inner training set: one
pass over the rows per group, so the cost grew with runs × rows. A linear fit on
centred, scaled columns needs only the training rows' count, means and scatter
matrix (the centred ``[X y]ᵀ[X y]``), and those of "every group but k" are the
totals minus group k's. One pass over the rows builds each group's moments; every
inner fold and its held-out squared error then costs O(p³), whatever the row count.

Sums are taken around the overall mean (``shift``) and each group's own mean, so
subtracting groups does not cancel large temperature levels against each other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Moments:
    """Count, column means and centred scatter of the rows ``[X y]`` (y the last column)."""

    count: float
    mean: np.ndarray  # (p + 1,)
    scatter: np.ndarray  # (p + 1, p + 1)

    @property
    def xx(self) -> np.ndarray:
        return self.scatter[:-1, :-1]

    @property
    def xy(self) -> np.ndarray:
        return self.scatter[:-1, -1]

    @property
    def yy(self) -> float:
        return float(self.scatter[-1, -1])

    def squared_errors(self, intercept: np.ndarray, coef: np.ndarray) -> np.ndarray:
        """Σ (y − b0 − X b)² over these rows for each column of ``coef`` (p, m): shape (m,)."""
        mean_x, mean_y = self.mean[:-1], self.mean[-1]
        spread = self.yy - 2.0 * (self.xy @ coef) + np.einsum("im,ij,jm->m", coef, self.xx, coef)
        offset = mean_y - intercept - mean_x @ coef
        return np.maximum(spread, 0.0) + self.count * offset**2


@dataclass(frozen=True)
class GroupMoments:
    """The moments of each group of rows, and of all rows but one group."""

    labels: np.ndarray  # (g,) group labels, in np.unique order
    counts: np.ndarray  # (g,)
    means: np.ndarray  # (g, p + 1)
    scatters: np.ndarray  # (g, p + 1, p + 1)

    @classmethod
    def of(cls, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> GroupMoments:
        labels, index = np.unique(groups, return_inverse=True)
        data = np.column_stack([X, y]).astype(float)
        counts = np.bincount(index, minlength=labels.size).astype(float)
        means = np.zeros((labels.size, data.shape[1]))
        np.add.at(means, index, data)
        means /= counts[:, None]
        scatters = np.empty((labels.size, data.shape[1], data.shape[1]))
        order = np.argsort(index, kind="stable")
        bounds = np.r_[0, np.cumsum(counts).astype(int)]
        for k in range(labels.size):
            centred = data[order[bounds[k] : bounds[k + 1]]] - means[k]
            scatters[k] = centred.T @ centred
        return cls(labels=labels, counts=counts, means=means, scatters=scatters)

    def group(self, k: int) -> Moments:
        return Moments(float(self.counts[k]), self.means[k], self.scatters[k])

    def without(self, k: int) -> Moments:
        """The moments of every row outside group ``k`` (pooled by the parallel-axis rule)."""
        keep = np.arange(self.labels.size) != k
        counts = self.counts[keep]
        total = float(counts.sum())
        mean = counts @ self.means[keep] / total
        offsets = self.means[keep] - mean
        scatter = self.scatters[keep].sum(axis=0) + (offsets.T * counts) @ offsets
        return Moments(total, mean, scatter)
