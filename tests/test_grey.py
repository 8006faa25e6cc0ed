"""Grey absolute degree of incidence (Liu & Lin 2010, §3.3): hand-worked checks."""

from __future__ import annotations

import numpy as np
import pytest

from models.estimators.parts.grey_incidence import absolute_degree, absolute_degrees


def test_hand_worked_example() -> None:
    # X0 = [1, 2, 4, 5] → zero-start image [0, 1, 3, 4]
    #   s0 = 1 + 3 + ½·4 = 6
    # X1 = [2, 3, 3, 6] → zero-start image [0, 1, 1, 4]
    #   s1 = 1 + 1 + ½·4 = 4
    # difference of images [0, 0, −2, 0] → s1 − s0 = 0 + (−2) + ½·0 = −2, |·| = 2
    # ε = (1 + 6 + 4) / (1 + 6 + 4 + 2) = 11/13
    x0 = np.array([1.0, 2.0, 4.0, 5.0])
    x1 = np.array([2.0, 3.0, 3.0, 6.0])
    assert absolute_degree(x0, x1) == pytest.approx(11 / 13, rel=0, abs=1e-12)


def test_hand_worked_two_samples_and_opposite_signs() -> None:
    # n = 2: no middle terms, s = ½ x⁰(2).
    # X0 = [0, 4] → s0 = 2;  X1 = [1, −1] → image [0, −2], s1 = −1
    # |s1 − s0| = |−1 − 2| = 3;  ε = (1 + 2 + 1) / (1 + 2 + 1 + 3) = 4/7
    assert absolute_degree(np.array([0.0, 4.0]), np.array([1.0, -1.0])) == pytest.approx(
        4 / 7, rel=0, abs=1e-12
    )


def test_identical_and_shifted_sequences_give_one() -> None:
    x = np.array([0.3, 1.2, 2.9, 3.1, 3.0])
    assert absolute_degree(x, x) == 1.0
    assert absolute_degree(x, x + 17.5) == pytest.approx(1.0, abs=1e-12)


def test_range_and_symmetry() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(2, 30))
        a = rng.normal(0, 10, n)
        b = rng.normal(0, 10, n)
        e = absolute_degree(a, b)
        assert 0.5 < e <= 1.0
        assert e == pytest.approx(absolute_degree(b, a), abs=1e-15)


def test_unit_sensitive() -> None:
    # Same shape, different scale: the areas differ, so ε < 1.
    x = np.array([0.0, 1.0, 2.0, 3.0])
    assert absolute_degree(x, 10 * x) < 0.7


def test_columns_match_single_degree() -> None:
    rng = np.random.default_rng(1)
    ref = rng.normal(size=12)
    seqs = rng.normal(size=(12, 4))
    got = absolute_degrees(ref, seqs)
    expected = [absolute_degree(ref, seqs[:, j]) for j in range(4)]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-15)


def test_segments_weighted_by_length_by_hand() -> None:
    # Run 0: X0 = [1, 2, 4, 5], X1 = [2, 3, 3, 6] → 11/13 (see the hand example).
    # Run 1: X0 = [0, 4], X1 = [1, −1]            → 4/7.
    # Run 2: one sample only → skipped.
    # Weighted mean: (4·11/13 + 2·4/7) / (4 + 2).
    ref = np.array([1.0, 2.0, 4.0, 5.0, 0.0, 4.0, 9.0])
    seq = np.array([2.0, 3.0, 3.0, 6.0, 1.0, -1.0, 3.0])
    segments = np.array([0, 0, 0, 0, 1, 1, 2])
    got = absolute_degrees(ref, seq[:, None], segments=segments)
    expected = (4 * 11 / 13 + 2 * 4 / 7) / 6
    assert got.shape == (1,)
    assert got[0] == pytest.approx(expected, rel=0, abs=1e-12)
    # Without segments it is one long sequence, a different number.
    assert absolute_degrees(ref, seq[:, None])[0] != pytest.approx(expected, abs=1e-6)


def test_segments_each_run_restarts_its_image() -> None:
    # Two runs whose second one starts at a high level: per-run images remove it.
    x = np.array([0.0, 1.0, 2.0, 50.0, 51.0, 52.0])
    segments = np.array([3, 3, 3, 8, 8, 8])
    assert absolute_degrees(x, (x - np.repeat([0.0, 50.0], 3))[:, None], segments)[0] == 1.0


def test_validation() -> None:
    with pytest.raises(ValueError, match="same length"):
        absolute_degree(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="at least 2 samples"):
        absolute_degree(np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match="finite"):
        absolute_degree(np.array([0.0, np.inf]), np.zeros(2))
    with pytest.raises(ValueError, match="sequences must be"):
        absolute_degrees(np.zeros(3), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="segments must be"):
        absolute_degrees(np.zeros(3), np.zeros((3, 2)), segments=np.zeros(2, dtype=int))
    with pytest.raises(ValueError, match="at least 2 samples"):
        absolute_degrees(np.zeros(3), np.zeros((3, 2)), segments=np.array([0, 1, 2]))
