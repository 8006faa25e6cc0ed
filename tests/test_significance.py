"""Tests of models.fit.significance: MANOVA (MATLAB manova1 d / p) and per-sensor ANOVA."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from statsmodels.formula.api import ols
from statsmodels.multivariate.manova import MANOVA
from statsmodels.stats.anova import anova_lm

from models.fit.significance import (
    AnovaResult,
    ManovaResult,
    anova_oneway,
    format_table,
    manova_oneway,
    speed_groups,
)


def grouped_data(
    seed: int, means: np.ndarray, per_group: int = 40, noise: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Normal samples around each row of ``means``; labels are 0, 2000, 4000, … r/min."""
    rng = np.random.default_rng(seed)
    g, p = means.shape
    labels = np.repeat(np.arange(g) * 2000, per_group)
    x = np.repeat(means, per_group, axis=0) + rng.normal(scale=noise, size=(g * per_group, p))
    return x, labels


def sscp(x: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """W and B computed directly from their definitions."""
    grand = x.mean(axis=0)
    W = np.zeros((x.shape[1], x.shape[1]))
    B = np.zeros_like(W)
    for label in np.unique(labels):
        part = x[labels == label]
        m = part.mean(axis=0)
        W += (part - m).T @ (part - m)
        B += len(part) * np.outer(m - grand, m - grand)
    return W, B


# --- Wilks' Λ against independent computations -------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wilks_lambda_matches_statsmodels_and_determinants(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    means = rng.normal(scale=0.5, size=(4, 3))
    x, labels = grouped_data(seed, means, per_group=15)
    res = manova_oneway(x, labels)

    df = pd.DataFrame(x, columns=["t1", "t2", "t3"])
    df["speed"] = labels
    mv = MANOVA.from_formula("t1 + t2 + t3 ~ C(speed)", data=df).mv_test()
    sm_wilks = float(mv.results["C(speed)"]["stat"].loc["Wilks' lambda", "Value"])
    assert res.wilks_lambda == pytest.approx(sm_wilks, abs=1e-10)

    W, B = sscp(x, labels)
    assert res.wilks_lambda == pytest.approx(np.linalg.det(W) / np.linalg.det(W + B), abs=1e-10)

    # eigenvalues are those of W⁻¹B, descending, s = min(p, g − 1) = 3 of them
    expected = np.sort(np.linalg.eigvals(np.linalg.solve(W, B)).real)[::-1][:3]
    np.testing.assert_allclose(res.eigenvalues, expected, rtol=1e-9)
    assert list(res.eigenvalues) == sorted(res.eigenvalues, reverse=True)


def test_chi2_is_bartlett_of_partial_wilks_and_dof_as_in_paper() -> None:
    # the paper's shape: p = 9 sensors, g = 5 speeds → s = 4, dof = 9·4, 8·3, 7·2, 6·1
    rng = np.random.default_rng(7)
    x, labels = grouped_data(7, rng.normal(size=(5, 9)), per_group=30)
    res = manova_oneway(x, labels)
    n, p, g = 150, 9, 5
    assert (res.n_samples, res.n_variables, res.n_groups) == (n, p, g)
    assert res.dof == (36, 24, 14, 6)
    lam = np.array(res.eigenvalues)
    for j in range(4):
        wilks_j = np.prod(1 / (1 + lam[j:]))
        chi2_j = -(n - 1 - (p + g) / 2) * math.log(wilks_j)
        assert res.chi2[j] == pytest.approx(chi2_j, rel=1e-12)
        assert res.p_values[j] == pytest.approx(stats.chi2.sf(chi2_j, res.dof[j]), rel=1e-9)


# --- hand example: 2 variables, 2 groups ---------------------------------------------------


def test_hand_example_two_variables_two_groups() -> None:
    # group A: (1,2) (3,2) (2,5), mean (2,3); deviations (−1,−1) (1,−1) (0,2)
    #   SSCP_A = [[1+1+0, 1−1+0], [., 1+1+4]] = [[2, 0], [0, 6]]
    # group B: (4,4) (6,4) (5,1), mean (5,3); deviations (−1,1) (1,1) (0,−2)
    #   SSCP_B = [[2, 0], [0, 6]]
    # W = [[4, 0], [0, 12]], δ = mean_B − mean_A = (3, 0), n1 = n2 = 3, n = 6
    # B = (n1 n2 / n) δ δᵀ has rank 1, so s = min(2, 1) = 1 and
    # λ_1 = (n1 n2 / n) δᵀ W⁻¹ δ = (9/6) · (3² / 4) = 1.5 · 2.25 = 27/8
    # Λ_0 = 1 / (1 + 27/8) = 8/35
    # Bartlett factor n − 1 − (p + g)/2 = 6 − 1 − (2 + 2)/2 = 3; χ²_0 = 3 ln(35/8)
    # dof_0 = (p − 0)(g − 1 − 0) = 2; for 2 dof, P(χ² > c) = exp(−c/2) → p_0 = (8/35)^1.5
    x = np.array([[1, 2], [3, 2], [2, 5], [4, 4], [6, 4], [5, 1]], dtype=float)
    labels = np.array(["A", "A", "A", "B", "B", "B"])
    res = manova_oneway(x, labels)
    assert res.eigenvalues == pytest.approx((27 / 8,), rel=1e-12)
    assert res.wilks_lambda == pytest.approx(8 / 35, rel=1e-12)
    assert res.chi2 == pytest.approx((3 * math.log(35 / 8),), rel=1e-12)
    assert res.dof == (2,)
    assert res.p_values == pytest.approx(((8 / 35) ** 1.5,), rel=1e-9)
    assert res.p_values[0] == pytest.approx(0.1093, abs=1e-4)
    assert res.d == 0  # 0.109 > 0.05: cannot reject equal means
    assert manova_oneway(x, labels, alpha=0.2).d == 1  # every p_j ≤ α → d = s


# --- the dimension d ---------------------------------------------------------------------


def one_direction_means() -> np.ndarray:
    u = np.array([1.0, 2.0, -1.0]) / math.sqrt(6)
    return np.outer([0.0, 5.0, 10.0, 15.0], u)  # 4 groups on one line in 3-D


def test_means_along_one_direction_give_d_1() -> None:
    x, labels = grouped_data(3, one_direction_means(), per_group=50)
    res = manova_oneway(x, labels)
    assert res.d == 1
    assert res.p_values[0] < 1e-100
    assert res.p_values[1] > 0.05
    # across seeds the j = 1 test wrongly rejects at about the α rate, so d = 1 in ~95 %
    # of them; 87 of 100 is the 0.1 % lower tail of Binomial(100, 0.945)
    ds = [
        manova_oneway(*grouped_data(s, one_direction_means(), per_group=50)).d for s in range(100)
    ]
    assert sum(d == 1 for d in ds) >= 87
    assert min(ds) >= 1


def test_no_group_effect_gives_d_0_in_most_seeds() -> None:
    ds = [manova_oneway(*grouped_data(s, np.zeros((5, 3)), per_group=30)).d for s in range(20)]
    assert sum(d == 0 for d in ds) >= 17


def test_means_spread_in_all_directions_give_d_s() -> None:
    means = np.vstack([np.zeros(3), 10 * np.eye(3)])  # 4 groups, affinely span 3-D
    x, labels = grouped_data(5, means, per_group=30)
    res = manova_oneway(x, labels)
    assert len(res.p_values) == 3
    assert all(p <= 0.05 for p in res.p_values)
    assert res.d == 3


def test_labels_may_be_any_hashable_and_order_does_not_matter() -> None:
    x, labels = grouped_data(11, one_direction_means(), per_group=20)
    as_text = np.array([f"{v} rpm" for v in labels], dtype=object)
    perm = np.random.default_rng(0).permutation(len(labels))
    a = manova_oneway(x, labels)
    b = manova_oneway(x[perm], as_text[perm])
    assert b.wilks_lambda == pytest.approx(a.wilks_lambda, rel=1e-10)
    assert b.d == a.d


# --- ANOVA -------------------------------------------------------------------------------


def test_anova_matches_scipy_and_statsmodels() -> None:
    rng = np.random.default_rng(21)
    labels = np.repeat([0, 2000, 4000, 6000, 8000], 12)
    x = np.column_stack(
        [
            rng.normal(size=60),  # ignores speed
            labels / 1000 + rng.normal(size=60),  # follows speed
        ]
    )
    res = anova_oneway(x, labels, ["T1", "T5"])
    assert [r.variable for r in res] == ["T1", "T5"]

    for col, r in enumerate(res):
        f, pv = stats.f_oneway(*(x[labels == v, col] for v in np.unique(labels)))
        assert r.f_stat == pytest.approx(f, rel=1e-12)
        assert r.p_value == pytest.approx(pv, rel=1e-12)
        assert (r.df_between, r.df_within) == (4, 55)

    df = pd.DataFrame({"t": x[:, 0], "speed": labels})
    table = anova_lm(ols("t ~ C(speed)", data=df).fit())
    assert res[0].f_stat == pytest.approx(table.loc["C(speed)", "F"], rel=1e-9)
    assert res[0].p_value == pytest.approx(table.loc["C(speed)", "PR(>F)"], rel=1e-9)

    assert not res[0].significant
    assert res[1].significant
    assert res[1].p_value < 1e-10


# --- refusals ----------------------------------------------------------------------------


GOOD_X, GOOD_LABELS = grouped_data(0, np.zeros((3, 2)), per_group=5)


@pytest.mark.parametrize(
    ("values", "groups", "message"),
    [
        (GOOD_X, np.zeros(15), "at least 2 groups"),
        (GOOD_X[:3], np.array([0, 1, 1]), "too few samples"),  # n − g = 1 < p = 2
        (np.where(np.eye(15, 2) == 1, np.nan, GOOD_X), GOOD_LABELS, "NaN or inf"),
        (np.where(np.eye(15, 2) == 1, np.inf, GOOD_X), GOOD_LABELS, "NaN or inf"),
        (GOOD_X, GOOD_LABELS[:-1], "shape mismatch"),
        (GOOD_X[:, 0], GOOD_LABELS, "2-D"),
        (np.empty((0, 2)), np.empty(0), "no samples"),
        (GOOD_X, np.where(np.arange(15) == 0, np.nan, GOOD_LABELS), "NaN or inf labels"),
        (GOOD_X, np.array([*GOOD_LABELS[:-1], float("nan")], dtype=object), "NaN or inf labels"),
        (np.column_stack([GOOD_X, 2 * GOOD_X[:, 0]]), GOOD_LABELS, "singular"),
        (np.column_stack([GOOD_X, GOOD_LABELS / 100]), GOOD_LABELS, "singular"),
    ],
)
def test_manova_refusals(values: np.ndarray, groups: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        manova_oneway(values, groups)


def test_alpha_outside_unit_interval_is_refused() -> None:
    with pytest.raises(ValueError, match="alpha"):
        manova_oneway(GOOD_X, GOOD_LABELS, alpha=1.5)


def test_anova_refusals() -> None:
    with pytest.raises(ValueError, match="2 names for 1 value columns"):
        anova_oneway(GOOD_X[:, :1], GOOD_LABELS, ["T1", "T2"])
    with pytest.raises(ValueError, match="at least 2 groups"):
        anova_oneway(GOOD_X, np.ones(15), ["T1", "T2"])
    with pytest.raises(ValueError, match="too few samples"):
        anova_oneway(GOOD_X[:2], np.array([0, 1]), ["T1", "T2"])
    constant = GOOD_X.copy()
    constant[:, 1] = 20.0
    with pytest.raises(ValueError, match="'T2' is constant"):
        anova_oneway(constant, GOOD_LABELS, ["T1", "T2"])


# --- speed_groups ------------------------------------------------------------------------


def test_speed_groups_rounds_to_nearest_band() -> None:
    speed = np.array([1998.0, 2003.0, 0.4, -3.0, 4049.9, 4050.0, 7960.0, 8012.0])
    np.testing.assert_array_equal(speed_groups(speed), [2000, 2000, 0, 0, 4000, 4100, 8000, 8000])
    assert not np.signbit(speed_groups(np.array([-3.0]))[0])  # 0, not −0
    np.testing.assert_array_equal(speed_groups(np.array([1740.0, 2260.0]), 500.0), [1500, 2500])
    with pytest.raises(ValueError, match="band_rpm"):
        speed_groups(speed, 0.0)
    with pytest.raises(ValueError, match="NaN or inf"):
        speed_groups(np.array([np.nan]))


# --- report ------------------------------------------------------------------------------


def test_format_table_and_as_dict() -> None:
    x, labels = grouped_data(3, one_direction_means(), per_group=50)
    manova = manova_oneway(x, labels)
    anova = anova_oneway(x, labels, ["T1", "T2", "T3"])
    anova.append(AnovaResult("T9", 0.5, 0.7, 3, 196, False))
    text = format_table(manova, anova)
    assert f"Wilks' lambda = {manova.wilks_lambda:.4g}" in text
    assert "d = 1" in text
    for j in range(3):
        assert f"{manova.chi2[j]:>12.4g} {manova.dof[j]:>5d} {manova.p_values[j]:>12.4g}" in text
    assert text.splitlines()[-2].startswith("T3")
    assert text.splitlines()[-2].endswith("speed-dependent")
    assert text.splitlines()[-1].startswith("T9") and text.splitlines()[-1].endswith("no")

    d = manova.as_dict()
    assert d["dof"] == [9, 4, 1] and d["d"] == 1 and isinstance(d["p_values"], list)
    assert isinstance(manova, ManovaResult)
    assert anova[0].as_dict()["variable"] == "T1"
