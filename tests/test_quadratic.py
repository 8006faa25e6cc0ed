"""Full quadratic response surface (MATLAB rstool 'quadratic', paper 000 §3.1)."""

from __future__ import annotations

import numpy as np
import pytest

from models.estimators.parts.quadratic import (
    fit_least_squares,
    n_quadratic_terms,
    quadratic_design,
    quadratic_terms,
)


def test_ten_terms_for_three_inputs_in_rstool_order() -> None:
    assert quadratic_terms(("x1", "x2", "x3")) == [
        "1",
        "x1",
        "x2",
        "x3",
        "x1*x2",
        "x1*x3",
        "x2*x3",
        "x1^2",
        "x2^2",
        "x3^2",
    ]


def test_design_columns_match_formulas_on_hand_example() -> None:
    design = quadratic_design(np.array([[2.0, 3.0, 5.0]]))
    np.testing.assert_array_equal(design, [[1, 2, 3, 5, 6, 10, 15, 4, 9, 25]])


def test_design_columns_follow_term_names() -> None:
    rng = np.random.default_rng(0)
    X = rng.normal(size=(7, 3))
    design = quadratic_design(X)
    env = {"x1": X[:, 0], "x2": X[:, 1], "x3": X[:, 2]}
    for column, term in zip(design.T, quadratic_terms(("x1", "x2", "x3")), strict=True):
        expected = np.ones(7) if term == "1" else eval(term.replace("^", "**"), {}, env)
        np.testing.assert_array_equal(column, expected)


@pytest.mark.parametrize(("k", "count"), [(1, 3), (2, 6), (3, 10), (4, 15), (5, 21)])
def test_term_count_formula(k: int, count: int) -> None:
    assert n_quadratic_terms(k) == count == 1 + k + k * (k - 1) // 2 + k
    assert len(quadratic_terms([f"x{i}" for i in range(k)])) == count
    assert quadratic_design(np.ones((4, k))).shape == (4, count)


def test_least_squares_recovers_known_coefficients() -> None:
    rng = np.random.default_rng(1)
    X = rng.uniform(-2, 2, size=(60, 3))
    design = quadratic_design(X)
    true = rng.normal(size=design.shape[1])
    np.testing.assert_allclose(fit_least_squares(design, design @ true), true, atol=1e-10)


def test_invalid_shapes() -> None:
    with pytest.raises(ValueError):
        quadratic_terms([])
    with pytest.raises(ValueError):
        quadratic_design(np.ones(3))
    with pytest.raises(ValueError):
        fit_least_squares(np.ones((4, 2)), np.ones(3))
