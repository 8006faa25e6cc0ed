"""PCA + quadratic estimator (paper 000): accuracy on synthetic data, exact JSON
round trip, units and refusal when unfitted."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.base import ModelInputs, NotFittedError
from models.estimators.pca_quadratic import PcaQuadraticModel

SENSORS = ("s0", "s1", "s2", "s3", "s4")
NOISE_UM = 0.5


def _synthetic(n: int, seed: int) -> tuple[ModelInputs, np.ndarray]:
    """Rises = overall level L times positive gains + a contrast D + small noise;
    error = known quadratic in L and speed (1000 r/min) + noise."""
    rng = np.random.default_rng(seed)
    level = rng.uniform(0.0, 20.0, n)
    contrast = rng.uniform(-6.0, 6.0, n)
    speed_rpm = rng.uniform(2000.0, 8000.0, n)
    gains = np.array([1.0, 0.8, 1.4, 0.6, 1.1])
    contrasts = np.array([1.0, -1.0, 0.5, -0.5, 0.0])
    rise = level[:, None] * gains + contrast[:, None] * contrasts + rng.normal(0, 0.02, (n, 5))
    s = speed_rpm / 1000.0
    error = 2.0 + 1.5 * level - 0.04 * level**2 + 3.0 * s + 0.1 * level * s - 0.2 * s**2
    error = error + rng.normal(0.0, NOISE_UM, n)
    return ModelInputs(rise_C=rise, sensors=SENSORS, speed_rpm=speed_rpm), error


@pytest.fixture(scope="module")
def fitted() -> PcaQuadraticModel:
    inputs, error = _synthetic(1500, seed=0)
    return PcaQuadraticModel().fit(inputs, error)


def test_predicts_held_out_data_to_the_noise(fitted: PcaQuadraticModel) -> None:
    test, error = _synthetic(1000, seed=1)
    rmse = float(np.sqrt(np.mean((error - fitted.predict(test)) ** 2)))
    assert 0.8 * NOISE_UM < rmse < 1.15 * NOISE_UM
    assert np.std(error) > 10 * NOISE_UM  # the task is not trivial


def test_fitted_structure(fitted: PcaQuadraticModel) -> None:
    assert fitted.sensors_used_ == SENSORS
    assert fitted.pca_.n_kept == 2  # like the paper: x1 alone explains ~83 % < 85 %
    assert 0.80 < fitted.pca_.cumulative[0] < 0.85
    assert np.all(fitted.pca_.components[:, 0] > 0)  # x1 = overall level
    assert fitted.terms_ == [
        "1",
        "x1",
        "x2",
        "speed_krpm",
        "x1*x2",
        "x1*speed_krpm",
        "x2*speed_krpm",
        "x1^2",
        "x2^2",
        "speed_krpm^2",
    ]
    assert fitted.coef_.shape == (10,)
    assert fitted.uses_speed


def test_json_round_trip_is_bit_identical(fitted: PcaQuadraticModel) -> None:
    hyper = json.loads(json.dumps(fitted.hyperparams()))
    params = json.loads(json.dumps(fitted.fitted_params()))
    loaded = PcaQuadraticModel.from_params(hyper, params)
    test, _ = _synthetic(500, seed=2)
    assert np.array_equal(loaded.predict(test), fitted.predict(test))
    assert loaded.sensors_used_ == fitted.sensors_used_
    assert loaded.terms_ == fitted.terms_


def test_fitted_params_content(fitted: PcaQuadraticModel) -> None:
    params = fitted.fitted_params()
    assert params["sensors"] == list(SENSORS)
    assert params["n_components"] == 2
    assert len(params["components"]) == 2
    assert all(len(loadings) == 5 for loadings in params["components"])
    assert len(params["eigenvalues"]) == 5
    assert len(params["coefficients_um"]) == len(params["terms"]) == 10
    assert params["threshold"] == 0.85
    assert set(params["inputs"]) == {"x1", "x2", "speed_krpm"}
    assert "1000 r/min" in params["inputs"]["speed_krpm"]
    assert "dimensionless" in params["inputs"]["x1"]


def test_input_units(fitted: PcaQuadraticModel) -> None:
    units = fitted.input_units()
    assert units["speed_krpm"].startswith("1000 r/min")
    assert units["speed_rpm"] == "r/min"
    assert all(units[name] == "°C rise" for name in SENSORS)
    assert "dimensionless" in units["x1"] and "dimensionless" in units["x2"]


def test_summary_lists_terms_with_units(fitted: PcaQuadraticModel) -> None:
    text = fitted.summary()
    assert "kept 2 component(s)" in text
    assert "x1*speed_krpm" in text
    assert text.count("µm") == 10


def test_unfitted_predict_raises() -> None:
    inputs, _ = _synthetic(10, seed=3)
    with pytest.raises(NotFittedError):
        PcaQuadraticModel().predict(inputs)


def test_sensor_subset_and_hyperparams() -> None:
    inputs, error = _synthetic(300, seed=4)
    model = PcaQuadraticModel(sensors=["s2", "s0"], threshold=0.9).fit(inputs, error)
    assert model.sensors_used_ == ("s2", "s0")
    assert model.hyperparams() == {"sensors": ["s2", "s0"], "threshold": 0.9}
    assert PcaQuadraticModel().hyperparams() == {"sensors": None, "threshold": 0.85}


def test_constant_sensor_is_named() -> None:
    inputs, error = _synthetic(100, seed=5)
    rise = inputs.rise_C.copy()
    rise[:, 3] = 0.0
    flat = ModelInputs(rise_C=rise, sensors=SENSORS, speed_rpm=inputs.speed_rpm)
    with pytest.raises(ValueError, match="'s3'"):
        PcaQuadraticModel().fit(flat, error)


def test_single_speed_warns_rank_deficient() -> None:
    inputs, error = _synthetic(200, seed=6)
    one_speed = ModelInputs(rise_C=inputs.rise_C, sensors=SENSORS, speed_rpm=np.full(200, 4000.0))
    with pytest.warns(RuntimeWarning, match="rank"):
        PcaQuadraticModel().fit(one_speed, error)
