"""Fuzzy c-means: hand-worked updates, convergence, invariances, validation."""

from __future__ import annotations

import numpy as np
import pytest

from models.estimators.parts.fcm import (
    fuzzy_c_means,
    sensor_points,
    update_centers,
    update_memberships,
    xie_beni,
)

# Four 1-D points in two obvious groups, symmetric about 5.
POINTS = np.array([0.0, 1.0, 9.0, 10.0])


def test_membership_update_by_hand_m2() -> None:
    # Centres v = [0.5, 9.5], m = 2, so 2/(m−1) = 2:
    #   u_1k = 1 / (1 + (d_1k / d_2k)²)
    # point 0:  d = 0.5, 9.5  → 1 / (1 + (0.5/9.5)²) = 1 / (1 + 1/361) = 361/362
    # point 1:  d = 0.5, 8.5  → 1 / (1 + (0.5/8.5)²) = 1 / (1 + 1/289) = 289/290
    # point 9:  d = 8.5, 0.5  → 1 / (1 + (8.5/0.5)²) = 1 / (1 + 289)   = 1/290
    # point 10: d = 9.5, 0.5  → 1 / (1 + 361)                          = 1/362
    # u_2k = 1 − u_1k.
    u = update_memberships(POINTS, np.array([0.5, 9.5]), m=2.0)
    expected_1 = np.array([361 / 362, 289 / 290, 1 / 290, 1 / 362])
    np.testing.assert_allclose(u[0], expected_1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(u[1], 1 - expected_1, rtol=0, atol=1e-12)


def test_membership_update_by_hand_m3() -> None:
    # m = 3 → 2/(m−1) = 1:  u_1k = 1 / (1 + d_1k / d_2k)
    # point 0: 1 / (1 + 0.5/9.5) = 9.5/10 = 0.95
    # point 1: 1 / (1 + 0.5/8.5) = 8.5/9  = 0.9444…
    u = update_memberships(POINTS, np.array([0.5, 9.5]), m=3.0)
    np.testing.assert_allclose(u[0, :2], [0.95, 8.5 / 9], rtol=0, atol=1e-12)


def test_point_on_a_centre_gets_full_membership() -> None:
    # Point 0 sits on centre 0 and point 10 on centre 1: memberships exactly 1 / 0.
    u = update_memberships(POINTS, np.array([0.0, 10.0]), m=2.0)
    assert u[:, 0].tolist() == [1.0, 0.0]
    assert u[:, 3].tolist() == [0.0, 1.0]
    np.testing.assert_allclose(u.sum(axis=0), 1.0, atol=1e-15)


def test_center_update_by_hand() -> None:
    # U row 1 = [0.8, 0.6, 0.4, 0.2], row 2 = 1 − row 1, m = 2 → weights u²:
    #   row 1: [0.64, 0.36, 0.16, 0.04], Σ = 1.2,
    #          Σ w x = 0 + 0.36·1 + 0.16·9 + 0.04·10 = 0.36 + 1.44 + 0.4 = 2.2
    #          v1 = 2.2 / 1.2 = 11/6
    #   row 2: [0.04, 0.16, 0.36, 0.64], Σ = 1.2,
    #          Σ w x = 0 + 0.16 + 3.24 + 6.4 = 9.8,  v2 = 9.8 / 1.2 = 49/6
    u1 = np.array([0.8, 0.6, 0.4, 0.2])
    v = update_centers(POINTS, np.vstack([u1, 1 - u1]), m=2.0)
    assert v.shape == (2, 1)
    np.testing.assert_allclose(v[:, 0], [11 / 6, 49 / 6], rtol=0, atol=1e-12)


def test_converged_clustering_separates_the_groups() -> None:
    result = fuzzy_c_means(POINTS, 2)
    assert result.labels.tolist() == [0, 0, 1, 1]
    v = result.centers[:, 0]
    # Symmetric data → symmetric centres, each within 0.01 of its group mean.
    # (Near v = 0.5 the weights u² are ≈ 0.9945 for point 0, 0.9931 for point 1,
    # 1.2e-5 and 7.6e-6 for points 9 and 10: v ≈ (0.9931 + 9·1.2e-5 + 10·7.6e-6)
    # / 1.9876 ≈ 0.4997, slightly below 0.5.)
    assert v[0] + v[1] == pytest.approx(10.0, abs=1e-8)
    assert v[0] == pytest.approx(0.4997, abs=1e-4)
    np.testing.assert_allclose(result.membership.sum(axis=0), 1.0, atol=1e-12)
    assert 0.9 < result.partition_coefficient() <= 1.0
    assert result.n_iter < 1000


def test_fixed_point_is_consistent() -> None:
    # At convergence one more update pair changes nothing.
    result = fuzzy_c_means(POINTS, 2, tol=1e-12)
    u = update_memberships(POINTS, update_centers(POINTS, result.membership))
    np.testing.assert_allclose(u, result.membership, atol=1e-10)


def test_independent_of_input_order() -> None:
    rng = np.random.default_rng(3)
    points = np.vstack(
        [rng.normal(0, 0.3, (6, 2)), rng.normal(5, 0.3, (6, 2)), rng.normal([0, 6], 0.3, (6, 2))]
    )
    perm = rng.permutation(len(points))
    a = fuzzy_c_means(points, 3)
    b = fuzzy_c_means(points[perm], 3)

    def groups(labels: np.ndarray, index: np.ndarray) -> set[frozenset[int]]:
        return {frozenset(index[labels == k].tolist()) for k in np.unique(labels)}

    assert groups(a.labels, np.arange(len(points))) == groups(b.labels, perm)
    assert len(groups(a.labels, np.arange(len(points)))) == 3
    order_a = np.lexsort(a.centers.T)
    order_b = np.lexsort(b.centers.T)
    np.testing.assert_allclose(a.centers[order_a], b.centers[order_b], atol=1e-6)
    assert a.objective == pytest.approx(b.objective, rel=1e-9)


def test_labels_numbered_by_first_member() -> None:
    points = np.array([10.0, 0.0, 10.5, 0.5, 20.0, 20.5])
    assert fuzzy_c_means(points, 3).labels.tolist() == [0, 1, 0, 1, 2, 2]


def test_objective_non_increasing_over_iterations() -> None:
    rng = np.random.default_rng(7)
    points = rng.normal(size=(30, 3))
    objectives = [
        fuzzy_c_means(points, 3, max_iter=k, n_init=1, tol=1e-15).objective for k in range(1, 25)
    ]
    steps = np.diff(objectives)
    assert np.all(steps <= 1e-12 * objectives[0])
    assert objectives[-1] < objectives[0]  # it actually moved


def test_deterministic_for_a_seed() -> None:
    rng = np.random.default_rng(11)
    points = rng.normal(size=(20, 2))
    a = fuzzy_c_means(points, 4, seed=5)
    b = fuzzy_c_means(points, 4, seed=5)
    np.testing.assert_array_equal(a.membership, b.membership)
    assert a.objective == b.objective


def test_xie_beni_matches_its_definition_and_prefers_true_count() -> None:
    result = fuzzy_c_means(POINTS, 2)
    u, v = result.membership, result.centers[:, 0]
    j = np.sum(u**2 * (POINTS[None, :] - v[:, None]) ** 2)
    assert xie_beni(POINTS, result) == pytest.approx(j / (4 * (v[1] - v[0]) ** 2), rel=1e-12)
    assert result.objective == pytest.approx(j, rel=1e-12)
    three = fuzzy_c_means(POINTS, 3)
    assert xie_beni(POINTS, result) < xie_beni(POINTS, three)


@pytest.mark.parametrize(
    ("points", "c", "m", "match"),
    [
        (POINTS, 1, 2.0, "n_clusters"),
        (POINTS, 5, 2.0, "n_clusters"),
        (POINTS, 2, 1.0, "m must be"),
        (np.array([0.0, np.nan, 1.0]), 2, 2.0, "finite"),
        (np.zeros((2, 2, 2)), 2, 2.0, "points must be"),
    ],
)
def test_validation(points: np.ndarray, c: int, m: float, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        fuzzy_c_means(points, c, m=m)


def test_sensor_points_zscore() -> None:
    t = np.linspace(0, 1, 50)
    base = 1 - np.exp(-3 * t)
    other = t**2
    rise = np.column_stack([base, 4.0 * base + 2.0, other, np.full_like(t, 3.0)])
    pts = sensor_points(rise)
    assert pts.shape == (4, 50)
    # proportional series (gain 4, offset 2) land on the same point
    np.testing.assert_allclose(pts[0], pts[1], atol=1e-12)
    # z-scored: mean 0, population sd 1; a constant sensor stays all-zero
    np.testing.assert_allclose(pts[:3].mean(axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(pts[:3].std(axis=1), 1.0, atol=1e-12)
    assert np.all(pts[3] == 0.0)
    # squared distance = 2n(1 − r)
    r = np.corrcoef(base, other)[0, 1]
    assert np.sum((pts[0] - pts[2]) ** 2) == pytest.approx(2 * 50 * (1 - r), rel=1e-10)


def test_sensor_points_validation() -> None:
    with pytest.raises(ValueError, match="at least 2 samples"):
        sensor_points(np.ones((1, 3)))
    with pytest.raises(ValueError, match="n_samples, p"):
        sensor_points(np.ones(5))


def test_high_dimensional_points_cluster_as_in_full_space() -> None:
    # 6 sensors × 400 samples: FCM runs on their 6-D span coordinates; the
    # memberships must equal plain iterations in the full 400-D space from the
    # same random start (the change of basis is orthonormal).
    from models.estimators.parts.fcm import _iterate

    rng = np.random.default_rng(7)
    base = rng.normal(size=(2, 400))
    points = np.vstack(
        [base[0] + 0.3 * rng.normal(size=(3, 400)), base[1] + 0.3 * rng.normal(size=(3, 400))]
    )
    result = fuzzy_c_means(points, 2, n_init=1, seed=3)
    start = np.random.default_rng(3).random((2, 6))
    start /= start.sum(axis=0)
    full_u, full_centers, _ = _iterate(points, start, 2.0, 1e-9, 1000)
    order = np.argsort(np.argmax(full_u, axis=0)[[0, 3]])  # label of point 0 first
    np.testing.assert_allclose(result.membership, full_u[order], atol=1e-9)
    np.testing.assert_allclose(result.centers, full_centers[order], atol=1e-9)
    assert result.centers.shape == (2, 400)
