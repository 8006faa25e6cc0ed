"""Fuzzy c-means clustering (Bezdek 1981), used to group temperature sensors.

Bezdek, J. C. (1981), *Pattern Recognition with Fuzzy Objective Function
Algorithms*, Plenum. For points x_1 … x_n (rows of ``points``) and c centres
v_1 … v_c, minimise

    J_m(U, V) = Σ_i Σ_k u_ik^m ‖x_k − v_i‖²,   Σ_i u_ik = 1,  u_ik ≥ 0,  m > 1

by alternating the two optimality conditions

    v_i  = Σ_k u_ik^m x_k / Σ_k u_ik^m                          (update_centers)
    u_ik = 1 / Σ_j (‖x_k − v_i‖ / ‖x_k − v_j‖)^{2/(m−1)}         (update_memberships)

until max |ΔU| < tol or max_iter updates. Each step can only lower J_m, so the
objective is non-increasing over the iterations. The start is a random
membership matrix drawn from ``seed``; ``n_init`` starts are run and the one
with the lowest J_m is kept. Hard labels are argmax memberships, renumbered so
cluster 0 holds point 0, the next new cluster the first point outside it, and
so on; the result is then the same whatever order the restarts found.

Paper 002 (Miao et al. 2015, §3) uses FCM to group the temperature *sensors*:
each sensor is one point whose coordinates are its temperature series, see
:func:`sensor_points`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FcmResult:
    """Outcome of :func:`fuzzy_c_means`.

    Attributes:
        centers: (c, d) cluster centres v_i.
        membership: (c, n) memberships u_ik; every column sums to 1.
        labels: (n,) hard label of each point (argmax membership), numbered in
            order of first member (point 0 is in cluster 0).
        objective: J_m of ``membership`` and ``centers``.
        n_iter: number of membership updates of the kept start.
    """

    centers: np.ndarray
    membership: np.ndarray
    labels: np.ndarray
    objective: float
    n_iter: int

    def partition_coefficient(self) -> float:
        """Bezdek's partition coefficient PC = (1/n) Σ_i Σ_k u_ik².

        1 for a crisp partition, 1/c for the fuzziest one (all u_ik = 1/c).
        """
        n = self.membership.shape[1]
        return float(np.sum(self.membership**2) / n)


def _as_points(points: np.ndarray) -> np.ndarray:
    """(n, d) float array; a 1-D array is n points in one dimension."""
    x = np.asarray(points, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2:
        raise ValueError(f"points must be (n, d) or (n,), got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("points must be finite (found NaN or inf)")
    return x


def _check_m(m: float) -> None:
    if not (np.isfinite(m) and m > 1):
        raise ValueError(f"fuzziness m must be a finite number > 1, got {m}")


def _squared_distances(x: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """(c, n) matrix of ‖x_k − v_i‖²."""
    return np.sum((centers[:, None, :] - x[None, :, :]) ** 2, axis=2)


def update_centers(points: np.ndarray, membership: np.ndarray, m: float = 2.0) -> np.ndarray:
    """One centre update: v_i = Σ_k u_ik^m x_k / Σ_k u_ik^m (Bezdek 1981).

    Returns (c, d) centres. A cluster with zero total weight (every point sits
    exactly on another centre, a degenerate case) gets the plain mean of the
    points so the next membership update stays defined.
    """
    x = _as_points(points)
    _check_m(m)
    u = np.asarray(membership, dtype=float)
    if u.ndim != 2 or u.shape[1] != x.shape[0]:
        raise ValueError(f"membership must be (c, {x.shape[0]}), got shape {u.shape}")
    weights = u**m
    total = weights.sum(axis=1)
    centers = np.tile(x.mean(axis=0), (u.shape[0], 1))
    used = total > 0
    centers[used] = (weights[used] @ x) / total[used, None]
    return centers


def update_memberships(points: np.ndarray, centers: np.ndarray, m: float = 2.0) -> np.ndarray:
    """One membership update (Bezdek 1981):

        u_ik = 1 / Σ_j (‖x_k − v_i‖ / ‖x_k − v_j‖)^{2/(m−1)}

    computed as u_ik ∝ (‖x_k − v_i‖²)^{−1/(m−1)} in logs, so no power under- or
    overflows. A point sitting exactly on a centre gets membership 1 there and 0
    elsewhere (shared equally if several centres coincide on it).

    Returns the (c, n) membership matrix; its columns sum to 1.
    """
    x = _as_points(points)
    _check_m(m)
    v = np.asarray(centers, dtype=float)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape[1] != x.shape[1]:
        raise ValueError(f"centers must be (c, {x.shape[1]}), got shape {v.shape}")
    d2 = _squared_distances(x, v)
    on_centre = d2 == 0
    with np.errstate(divide="ignore"):
        log_w = -np.log(d2) / (m - 1)
    hit = on_centre.any(axis=0)
    log_w[:, hit] = 0.0  # overwritten below; avoids inf − inf
    log_w -= log_w.max(axis=0)
    u = np.exp(log_w)
    u /= u.sum(axis=0)
    u[:, hit] = on_centre[:, hit] / on_centre[:, hit].sum(axis=0)
    return u


def _objective(x: np.ndarray, u: np.ndarray, centers: np.ndarray, m: float) -> float:
    return float(np.sum(u**m * _squared_distances(x, centers)))


def _relabel(u: np.ndarray, centers: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Renumber clusters in order of their first member; unused clusters go last."""
    labels = np.argmax(u, axis=0)
    order: list[int] = []
    for label in labels:
        if label not in order:
            order.append(int(label))
    order += [i for i in range(u.shape[0]) if i not in order]
    new_of_old = np.empty(len(order), dtype=int)
    new_of_old[order] = np.arange(len(order))
    return u[order], centers[order], new_of_old[labels]


def _iterate(
    x: np.ndarray, u: np.ndarray, m: float, tol: float, max_iter: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """Alternate centre and membership updates from ``u``; (u, centres, n_iter)."""
    n_iter = 0
    while n_iter < max_iter:
        n_iter += 1
        centers = update_centers(x, u, m)
        u_new = update_memberships(x, centers, m)
        change = float(np.max(np.abs(u_new - u)))
        u = u_new
        if change < tol:
            break
    return u, centers, n_iter


def span_coordinates(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (n, r) of n points in an orthonormal basis (r, d) of their span.

    Centres are weighted means of the points, so they stay in that span, and
    every distance the algorithm needs is the same in these coordinates (an
    orthonormal change of basis). Sensors as points have one coordinate per
    sample (d up to millions) but there are only p of them: clustering their
    p-dimensional coordinates gives the same result at a cost independent of d.
    """
    _, _, basis = np.linalg.svd(x, full_matrices=False)
    return x @ basis.T, basis


def fuzzy_c_means(
    points: np.ndarray,
    n_clusters: int,
    m: float = 2.0,
    tol: float = 1e-9,
    max_iter: int = 1000,
    seed: int = 0,
    n_init: int = 10,
) -> FcmResult:
    """Cluster the rows of ``points`` (n, d) into ``n_clusters`` fuzzy clusters.

    Each iteration computes centres from the memberships, then memberships from
    those centres; it stops when the largest membership change is below ``tol``
    or after ``max_iter`` iterations. ``n_init`` random starts (memberships drawn
    uniformly and normalised, from ``numpy.random.default_rng(seed)``); the one
    with the lowest J_m wins. Deterministic for a given seed.

    Raises:
        ValueError: unless 2 ≤ n_clusters ≤ n, m > 1, the points are finite,
            tol > 0, max_iter ≥ 1 and n_init ≥ 1.
    """
    x = _as_points(points)
    n = x.shape[0]
    c = int(n_clusters)
    if c != n_clusters or not 2 <= c <= n:
        raise ValueError(f"n_clusters must be an integer with 2 ≤ c ≤ {n} points, got {n_clusters}")
    _check_m(m)
    if not tol > 0:
        raise ValueError(f"tol must be > 0, got {tol}")
    if max_iter < 1 or n_init < 1:
        raise ValueError(f"max_iter and n_init must be ≥ 1, got {max_iter} and {n_init}")

    basis = None
    if x.shape[1] > n:
        x, basis = span_coordinates(x)

    rng = np.random.default_rng(seed)
    best: tuple[float, np.ndarray, np.ndarray, int] | None = None
    for _ in range(n_init):
        u = rng.random((c, n))
        u /= u.sum(axis=0)
        u, centers, n_iter = _iterate(x, u, m, tol, max_iter)
        objective = _objective(x, u, centers, m)
        if best is None or objective < best[0]:
            best = (objective, u, centers, n_iter)

    assert best is not None  # n_init ≥ 1 starts
    objective, u, centers, n_iter = best
    if basis is not None:
        centers = centers @ basis
    u, centers, labels = _relabel(u, centers)
    return FcmResult(
        centers=centers, membership=u, labels=labels, objective=objective, n_iter=n_iter
    )


def xie_beni(points: np.ndarray, result: FcmResult, m: float = 2.0) -> float:
    """Xie–Beni validity index: J_m / (n · min_{i≠j} ‖v_i − v_j‖²).

    Xie, X. L. & Beni, G. (1991), "A validity measure for fuzzy clustering",
    IEEE Trans. PAMI 13(8), 841–847 (defined there for m = 2). Compactness over
    separation: lower is better. Infinite if two centres coincide.
    """
    x = _as_points(points)
    _check_m(m)
    v = result.centers
    if result.membership.shape[1] != x.shape[0] or v.shape[1] != x.shape[1]:
        raise ValueError("result does not belong to these points (shapes differ)")
    compactness = _objective(x, result.membership, v, m)
    separation = _squared_distances(v, v)
    np.fill_diagonal(separation, np.inf)
    min_sep = float(separation.min())
    if min_sep == 0:
        return float("inf")
    return compactness / (x.shape[0] * min_sep)


def sensor_points(rise_C: np.ndarray) -> np.ndarray:
    """Turn (n_samples, p) temperature rises into p points (p, n_samples) for FCM.

    Each sensor's series is z-scored: z = (x − mean) / sd with the population sd
    (ddof = 0), so every non-constant row has mean 0 and ‖z‖² = n. A constant
    sensor has no shape and stays all-zero.

    Why: the sensors are grouped by the heat source that drives them, which shows
    in the *shape* of the response (time constant, delay), not its size. Two
    sensors on the same bearing housing, one near and one farther from the race,
    rise with the same shape but different gains; raw rises would put them in
    different clusters by amplitude. After z-scoring,

        ‖z_a − z_b‖² = 2n (1 − r_ab),

    with r_ab the Pearson correlation, so Euclidean FCM clusters by correlation
    and proportional series (any positive gain, any offset) land on the same point.
    """
    rise = np.asarray(rise_C, dtype=float)
    if rise.ndim != 2:
        raise ValueError(f"rise_C must be (n_samples, p), got shape {rise.shape}")
    if rise.shape[0] < 2:
        raise ValueError(f"need at least 2 samples per sensor, got {rise.shape[0]}")
    if not np.all(np.isfinite(rise)):
        raise ValueError("rise_C must be finite (found NaN or inf)")
    centred = rise - rise.mean(axis=0)
    sd = rise.std(axis=0)
    constant = np.ptp(rise, axis=0) == 0
    z = np.zeros_like(centred)
    z[:, ~constant] = centred[:, ~constant] / sd[~constant]
    return z.T
