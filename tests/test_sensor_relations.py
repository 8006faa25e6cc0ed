"""models.estimators.sensor_relations: each sensor's rise from the others', checked on
hand-worked data."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.estimators.sensor_relations import SensorRelations, fit_relations

# Two sensors, four rows: A = 0, 1, 2, 3 and B = 1, 3, 5, 8 (°C rises).
# Means 1.5 and 4.25; with covariances divided by n = 4:
#   var A = 1.25, cov AB = 2.875, var B = 6.6875.
# B from A: b = 2.875 / 1.25 = 2.3, a = 4.25 − 2.3 · 1.5 = 0.8; residuals 0.2, −0.1,
#   −0.4, 0.3, so σ = √(0.30 / 4) = 0.27386.
# A from B: b = 2.875 / 6.6875 = 0.429907, a = 1.5 − 0.429907 · 4.25 = −0.327103.
X = np.array([[0.0, 1.0], [1.0, 3.0], [2.0, 5.0], [3.0, 8.0]])


def test_relation_of_two_sensors_by_hand() -> None:
    relations = fit_relations(X, ["A", "B"])
    intercept, coefficients, sigma = relations.relation("B", ["A"])
    assert intercept == pytest.approx(0.8)
    assert coefficients == {"A": pytest.approx(2.3)}
    assert sigma == pytest.approx(np.sqrt(0.30 / 4))
    intercept, coefficients, sigma = relations.relation("A", ["B"])
    assert coefficients == {"B": pytest.approx(2.875 / 6.6875)}
    assert intercept == pytest.approx(1.5 - 2.875 / 6.6875 * 4.25)
    # One run: the held-out σ is the in-sample σ.
    assert relations.held_out_sigma_C["B"] == pytest.approx(np.sqrt(0.30 / 4))
    assert relations.runs == 1 and relations.rows == 4


def test_held_out_sigma_leaves_each_run_out_by_hand() -> None:
    # Runs: rows 0–1 and rows 2–3. B from A fitted on run 1: B = 1 + 2A, so run 2
    # (A = 2, 3) is predicted 5, 7: residuals 0, 1. Fitted on run 2: B = 3A − 1, run 1
    # predicted −1, 2: residuals 2, 1. Pooled RMS √(6 / 4).
    # A from B on run 1: A = (B − 1) / 2 → run 2 residuals 0, −0.5; on run 2:
    # A = (B − 5) / 3 + 2 → run 1 residuals −2/3, −1/3. RMS √((0.25 + 4/9 + 1/9) / 4).
    relations = fit_relations(X, ["A", "B"], run_index=np.array([0, 0, 1, 1]))
    assert relations.runs == 2
    assert relations.held_out_sigma_C["B"] == pytest.approx(np.sqrt(6 / 4))
    assert relations.held_out_sigma_C["A"] == pytest.approx(np.sqrt((0.25 + 4 / 9 + 1 / 9) / 4))


def three_sensors(noise_C: float = 0.0, rows: int = 200) -> np.ndarray:
    """C = 0.5 + 2 A − B exactly (plus optional noise on C)."""
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 10, rows)
    b = rng.uniform(0, 5, rows)
    c = 0.5 + 2 * a - b + rng.normal(0, noise_C, rows) if noise_C else 0.5 + 2 * a - b
    return np.column_stack([a, b, c])


def test_an_exact_relation_is_recovered_and_predicts_from_any_subset() -> None:
    relations = fit_relations(three_sensors(), ["A", "B", "C"])
    intercept, coefficients, sigma = relations.relation("C", ["A", "B"])
    assert intercept == pytest.approx(0.5)
    assert coefficients == {"A": pytest.approx(2.0), "B": pytest.approx(-1.0)}
    assert sigma == pytest.approx(0.0, abs=1e-6)
    said = relations.predict("C", {"A": 3.0, "B": 1.0, "C": 99.0})  # C's own value unused
    assert said.predicted_rise_C == pytest.approx(5.5)
    assert said.using == ("A", "B")
    # A from B and C: A = (C + B − 0.5) / 2.
    assert relations.predict("A", {"B": 1.0, "C": 5.5}).predicted_rise_C == pytest.approx(3.0)


def test_sigma_grows_when_a_needed_sensor_is_missing() -> None:
    relations = fit_relations(
        three_sensors(noise_C=0.1), ["A", "B", "C"], run_index=np.repeat([0, 1], 100)
    )
    full = relations.predict("C", {"A": 3.0, "B": 1.0})
    without_b = relations.predict("C", {"A": 3.0})
    assert full.sigma_C == pytest.approx(relations.held_out_sigma_C["C"])
    assert 0.08 < full.sigma_C < 0.12  # the noise put on C
    assert without_b.sigma_C > 5 * full.sigma_C  # B spans 0–5 °C and is now unexplained
    assert without_b.using == ("A",)


def test_document_round_trip_is_plain_json() -> None:
    relations = fit_relations(three_sensors(0.1), ["A", "B", "C"], np.repeat([0, 1], 100))
    document = json.loads(json.dumps(relations.as_document()))
    again = SensorRelations.from_document(document)
    assert again.sensors == relations.sensors
    assert again.held_out_sigma_C == relations.held_out_sigma_C
    np.testing.assert_array_equal(again.covariance_C2, relations.covariance_C2)
    assert [r.rows for r in again.per_run] == [100, 100]
    explicit = document["relations"]["C"]
    assert explicit["coefficients_C_per_C"]["A"] == pytest.approx(2.0, abs=0.01)
    assert set(explicit) == {
        "intercept_C",
        "coefficients_C_per_C",
        "residual_sigma_C",
        "held_out_sigma_C",
    }


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["per_run"][0].pop("covariance_C2"), "missing field 'covariance_C2'"),
        (lambda d: d.update(rows=5), "'rows'/'runs' do not match 'per_run'"),
        (lambda d: d["per_run"][0].update(mean_rise_C=[0.0]), "do not match 3 sensors"),
        (lambda d: d["per_run"][1]["covariance_C2"][0].__setitem__(1, 123.0), "symmetric"),
    ],
)
def test_a_damaged_document_is_refused(change, message: str) -> None:
    relations = fit_relations(three_sensors(0.1), ["A", "B", "C"], np.repeat([0, 1], 100))
    document = relations.as_document()
    change(document)
    with pytest.raises(ValueError, match=message):
        SensorRelations.from_document(document)


def test_too_little_data_is_refused() -> None:
    with pytest.raises(ValueError, match="more rows"):
        fit_relations(X[:2], ["A", "B"])
    with pytest.raises(ValueError, match="finite"):
        fit_relations(np.array([[0.0, 1.0], [np.nan, 2.0], [1.0, 3.0]]), ["A", "B"])
    with pytest.raises(ValueError, match="two or more"):
        fit_relations(X[:, :1], ["A"])
