"""Fitting on a subset of rows is fitting the method, not least squares under its name.

Validation (``fit``'s leave-one-run-out), the residual analysis and ``replay`` fit
each method on all rows but a held-out run through ``fit_rows``. mlr's fast path
(rows read straight into its design) had been inherited by grey-mlr, ridge and PLS,
so their held-out figures were mlr's; and the analysis refitted a ridge or PLS base's
sensor coefficients by least squares, undoing the penalty.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models import signing
from models.analysis import augmented
from models.analysis.search import ResidualAnalysis, analyze
from models.data.dataset import load_runs
from models.data.features import Prepared, prepare
from models.estimators.registry import make_model
from models.online.streaming import StreamingAugmented
from tests import independent_shaft
from tests.test_effect_stream import streamed

ROOT = Path(__file__).resolve().parents[1]
FL_THERMAL = ROOT / "data" / "fl_thermal.csv"


@pytest.fixture(scope="module")
def fl_ch1() -> Prepared:
    return prepare(load_runs(FL_THERMAL, target="ch1_um")).without_sensor_readings()


@pytest.mark.parametrize("method", ["mlr", "grey-mlr", "ridge", "pls", "pca-quadratic"])
def test_fit_rows_is_fit_on_the_rows_taken(fl_ch1: Prepared, method: str) -> None:
    rows = np.asarray(fl_ch1.data.run) != "c3_3750rpm"
    inputs, y = fl_ch1.inputs, fl_ch1.error_um
    by_rows = make_model(method).fit_rows(inputs, y, rows)
    taken = make_model(method).fit(inputs.take(rows), y[rows])
    assert by_rows.sensors_used_ == taken.sensors_used_
    assert by_rows.fitted_params() == taken.fitted_params()
    np.testing.assert_allclose(by_rows.predict(inputs), taken.predict(inputs), atol=1e-9)


def test_grey_mlr_selects_its_sensors_when_fitted_on_rows(fl_ch1: Prepared) -> None:
    rows = np.asarray(fl_ch1.data.run) != "c6_steps"
    model = make_model("grey-mlr").fit_rows(fl_ch1.inputs, fl_ch1.error_um, rows)
    assert 0 < len(model.sensors_used_) < len(fl_ch1.inputs.sensors)


@pytest.mark.parametrize("method", ["ridge", "pls"])
def test_a_penalised_base_keeps_its_penalty_in_the_analysis(fl_ch1: Prepared, method) -> None:
    """Its design is one column, its penalised prediction, fitted per fold."""
    penalised = ResidualAnalysis(fl_ch1, method)
    assert not penalised.base.fixed
    for fold, model in enumerate(penalised.base.models):
        design = penalised.base.design(fold)
        assert design.shape == (fl_ch1.data.n_samples, 1)
        np.testing.assert_allclose(design[:, 0], model.predict(fl_ch1.inputs))
    plain = ResidualAnalysis(fl_ch1, "mlr")
    before_penalised = penalised.evaluate([], None).predicted_um
    before_plain = plain.evaluate([], None).predicted_um
    assert np.max(np.abs(before_penalised - before_plain)) > 1.0  # µm: not mlr under a name


@pytest.fixture(scope="module")
def shaft(tmp_path_factory: pytest.TempPathFactory) -> Prepared:
    path = independent_shaft.write_csv(
        tmp_path_factory.mktemp("shaft") / "lag.csv", "thermal_lag", 2
    )
    return prepare(load_runs(path))


def _document(prepared: Prepared, method: str) -> tuple[dict, np.ndarray]:
    result, accepted, analysis = analyze(prepared, method)
    assert accepted, "the shaft's hidden lag is found on either base"
    document = augmented.build_augmented_document(analysis, accepted, result, "m", "test")
    return document, augmented.augmented_prediction(analysis, accepted)


def test_a_stored_ridge_base_predicts_and_streams_as_fitted(shaft: Prepared) -> None:
    document, fitted = _document(shaft, "ridge")
    assert document["format_version"] == augmented.FORMAT_VERSION == 2
    np.testing.assert_allclose(augmented.predict(document, shaft), fitted, atol=1e-9)
    np.testing.assert_allclose(streamed(document, shaft), fitted, atol=1e-6)


def test_a_ridge_base_stored_before_format_2_still_loads_as_it_was_fitted(
    shaft: Prepared, tmp_path: Path
) -> None:
    """Format 1 stored a ridge base's sensors refitted by least squares: those are its terms."""
    document, fitted = _document(shaft, "mlr")
    old = json.loads(json.dumps(document))
    old["format_version"] = 1
    old["base"]["method"] = "ridge"
    old["base"]["params"]["penalty"] = 0.01
    old.pop("signature", None)  # signed again below, as models sign does for an old file
    old = augmented.sign(augmented.sealed(old), signing.key_for_store(tmp_path))
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old), encoding="utf-8")
    loaded = augmented.load(path)
    np.testing.assert_allclose(augmented.predict(loaded, shaft), fitted, atol=1e-9)
    assert StreamingAugmented(loaded).sensors  # the coefficient count checks out
    np.testing.assert_allclose(streamed(loaded, shaft), fitted, atol=1e-6)


def test_a_lag_ridge_base_known_at_probe_rows_is_fitted_with_its_whole_history(
    shaft: Prepared,
) -> None:
    """With the target known every 30th row (a probe), the augmented model's base is the
    lag-ridge fitted on those rows with its lags run over every row, not over the probe
    rows alone as if they followed one another."""
    known = np.zeros(shaft.data.n_samples, dtype=bool)
    known[::30] = True
    analysis = ResidualAnalysis(shaft, "lag-ridge", fit_rows=known)
    base, _, _ = augmented.fit_augmented(analysis, [])
    whole = make_model("lag-ridge").fit_rows(shaft.inputs, shaft.error_um, known)
    taken = make_model("lag-ridge").fit(shaft.inputs.take(known), shaft.error_um[known])
    assert base.fitted_params() == whole.fitted_params()
    assert base.fitted_params() != taken.fitted_params()
