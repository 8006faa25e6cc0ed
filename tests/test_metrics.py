"""Accuracy figures, checked by hand and against paper 000's Table 5."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from models.fit.metrics import accuracy, relative_error

DATA = Path(__file__).resolve().parent.parent / "data"


def test_accuracy_by_hand() -> None:
    # residuals e = [1, -1, 3]: RMSE = sqrt((1+1+9)/3) = sqrt(11/3);
    # mean 1, deviations [0, -2, 2] → σ = sqrt(8/2) = 2; max |e| = 3.
    acc = accuracy(np.array([2.0, 0.0, 4.0]), np.array([1.0, 1.0, 1.0]))
    assert acc.rmse_um == pytest.approx(np.sqrt(11 / 3), abs=1e-15)
    assert acc.sigma_um == pytest.approx(2.0, abs=1e-15)
    assert acc.max_abs_um == 3.0
    assert acc.n_samples == 3


def test_sigma_ignores_an_offset_rmse_does_not() -> None:
    measured = np.array([1.0, 2.0, 3.0, 4.0])
    acc = accuracy(measured, measured - 5.0)
    assert acc.sigma_um == 0.0 and acc.rmse_um == 5.0


def test_paper_000_table5_relative_errors() -> None:
    with (DATA / "seed000_table5_test.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    actual = np.array([float(r["actual_um"]) for r in rows])
    predicted = np.array([float(r["predicted_um"]) for r in rows])
    printed = np.array([float(r["relative_error"]) for r in rows])
    ours = relative_error(actual, predicted)
    np.testing.assert_allclose(ours, printed, atol=5e-5)
    assert int(np.sum(ours < 0.05)) == 43
    # The paper: accuracy drops at 8000 r/min (samples 41–50).
    speeds = np.array([float(r["speed_rpm"]) for r in rows])
    assert ours[speeds == 8000].mean() > ours[speeds < 8000].mean()


def test_relative_error_of_zero_measurement() -> None:
    np.testing.assert_array_equal(
        relative_error(np.array([0.0, 0.0]), np.array([0.0, 1.0])), [0.0, np.inf]
    )
