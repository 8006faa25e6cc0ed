"""Conditioning, bias sensitivity, regularised fits, and the runtime's refusal of fragile models."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gateway.config import MachineSection
from gateway.wiring import load_bank
from models.base import ModelInputs
from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.registry import make_model
from models.fit.conditioning import assess, bias_sensitivity, condition_number, variance_inflation
from models.fit.workflow import fit_and_store
from models.store import ModelStore
from tests.cli import ROOT, gateway_in_process
from tests.synthetic import write_runs_csv


def test_vif_and_condition_number_match_a_hand_computed_pair() -> None:
    # Centred columns [-1,0,1,0] and [-1,1,1,-1]: r = 2/√8, r² = 1/2, so VIF = 2 each;
    # the unit-norm design has singular values √(1 ± r): condition √((1+r)/(1-r)) = 1 + √2.
    X = np.array([[-1.0, -1.0], [0.0, 1.0], [1.0, 1.0], [0.0, -1.0]]) + np.array([20.0, 30.0])
    assert variance_inflation(X) == pytest.approx([2.0, 2.0])
    assert condition_number(X) == pytest.approx(1 + np.sqrt(2))


def test_independent_inputs_have_vif_one_and_a_constant_input_is_inseparable() -> None:
    X = np.array([[1.0, 1.0], [-1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]])
    assert variance_inflation(X) == pytest.approx([1.0, 1.0])
    assert condition_number(X) == pytest.approx(1.0)
    assert condition_number(np.column_stack([X[:, 0], np.ones(4)])) == np.inf


def exact_inputs(n: int = 200, seed: int = 1) -> tuple[ModelInputs, np.ndarray]:
    rng = np.random.default_rng(seed)
    rise = np.column_stack([np.linspace(0, 10, n), np.linspace(0, 6, n) ** 1.3])
    rise += rng.normal(0, 0.05, rise.shape)
    error = 2.0 + 3.0 * rise[:, 0] - 2.0 * rise[:, 1]
    return ModelInputs(rise, ("T1", "T2"), np.linspace(0, 6000, n)), error


def test_sensitivity_of_a_linear_model_is_its_coefficients() -> None:
    inputs, error = exact_inputs()
    model = make_model("mlr").fit(inputs, error)
    figures = assess(model, inputs, sensor_accuracy_C=0.5)
    assert figures.sensitivity_um_per_C == pytest.approx({"T1": 3.0, "T2": -2.0})
    assert figures.worst_sensor == "T1"
    assert figures.worst_single_um == pytest.approx(1.5)
    assert figures.worst_case_um == pytest.approx(2.5)
    record = figures.as_dict()
    assert json.loads(json.dumps(record)) == record  # plain JSON, no NaN/inf tokens


def test_sensitivity_of_a_nonlinear_model_is_its_mean_slope() -> None:
    inputs, error = exact_inputs()
    model = make_model("pca-quadratic").fit(inputs, error)
    sens = bias_sensitivity(model, inputs)
    # The same figure by a wider central difference on every row.
    for i, name in enumerate(inputs.sensors):
        up, down = inputs.rise_C.copy(), inputs.rise_C.copy()
        up[:, i] += 0.5
        down[:, i] -= 0.5
        slope = (
            model.predict(ModelInputs(up, inputs.sensors, inputs.speed_rpm))
            - model.predict(ModelInputs(down, inputs.sensors, inputs.speed_rpm))
        ) / 1.0
        assert sens[name] == pytest.approx(float(np.mean(slope)), rel=0.05, abs=0.05)


def collinear_runs(seed: int = 2, k: int = 6) -> tuple[ModelInputs, np.ndarray]:
    """Four runs of ``k`` sensors that follow one heat source within slow 0.01 °C walks.

    The error follows the source (2.5 µm/°C) plus a slow random walk of its own,
    which least squares fits with large balanced coefficients on the walks.
    """
    rng = np.random.default_rng(seed)
    rises, errors, runs = [], [], []
    for run in range(4):
        t = np.linspace(0, 1, 150)
        source = (6 + run) * (1 - np.exp(-3 * t))
        walks = np.cumsum(rng.normal(0, 0.01, (t.size, k)), axis=0)
        rises.append(source[:, None] + walks)
        errors.append(2.5 * source + np.cumsum(rng.normal(0, 0.1, t.size)))
        runs.append(np.full(t.size, run))
    rise = np.vstack(rises)
    names = tuple(f"T{i + 1}" for i in range(k))
    inputs = ModelInputs(rise, names, np.zeros(len(rise)), np.concatenate(runs))
    return inputs, np.concatenate(errors)


@pytest.mark.parametrize("method", ["ridge", "pls"])
def test_regularised_fits_are_far_less_sensitive_to_a_bias_than_least_squares(method) -> None:
    inputs, error = collinear_runs()
    plain = assess(make_model("mlr").fit(inputs, error), inputs)
    regularised = assess(make_model(method).fit(inputs, error), inputs)
    assert plain.condition_number > 30  # the data cannot separate T1 from T2
    assert plain.worst_single_um > 3 * regularised.worst_single_um
    # The physics is kept: the sensitivities of the pair still add up to the true 2.5 µm/°C.
    assert sum(regularised.sensitivity_um_per_C.values()) == pytest.approx(2.5, abs=0.2)


def test_the_penalty_is_chosen_without_the_held_out_run() -> None:
    inputs, error = collinear_runs()
    train = inputs.run_index != 3
    model = make_model("ridge").fit(inputs.take(train), error[train])
    changed = error.copy()
    changed[~train] += 50.0  # whatever the held-out run holds, the fit on the others is the same
    again = make_model("ridge").fit(inputs.take(train), changed[train])
    assert model.fitted_params() == again.fitted_params()


def test_fit_prints_conditioning_and_warns_on_a_fragile_model(tmp_path: Path) -> None:
    out = tmp_path / "fit.json"
    result = gateway_in_process(
        "fit", ROOT / "data" / "fl_thermal.csv", "--method", "mlr", "--target", "ch5_um",
        "--store", tmp_path / "store", "--json", out, "--no-progress",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "condition number" in result.stdout and "µm per °C bias" in result.stdout
    assert "warning: mlr-ch5_um-all: a bias of ±0.5 °C on T3" in result.stderr
    record = json.loads(out.read_text())["conditioning"]["mlr-ch5_um-all"]
    assert max(record["vif"].values()) > 1000
    assert record["worst_sensor"] == "T3"
    assert record["sensitivity_um_per_C"]["T3"] == pytest.approx(20.46, abs=0.01)
    stored = json.loads((tmp_path / "store" / "mlr-ch5_um-all.json").read_text())
    assert stored["conditioning"]["worst_single_um"] == pytest.approx(10.23, abs=0.01)


def machine(store: Path, model_id: str, limit_um: float) -> MachineSection:
    return MachineSection.model_validate(
        {
            "id": "m1",
            "transmitters": [
                {
                    "name": "bus",
                    "tcp": {"host": "127.0.0.1", "port": 5020},
                    "devices": [
                        {"device_id": 1, "channels": [f"T{i + 1}" for i in range(6)]},
                    ],
                }
            ],
            "cnc": {"modbus": {"host": "127.0.0.1", "port": 5021}},
            "models": {
                "store": str(store),
                "regimes": {"fallback_model": model_id},
                "max_bias_error_um": limit_um,
            },
        }
    )


def fragile_store(tmp_path: Path) -> Path:
    """One mlr and one ridge model of the same collinear data, as ``fit`` saves them."""
    inputs, error = collinear_runs()
    rows = ["run,time_s,speed_rpm," + ",".join(inputs.sensors) + ",error_um"]
    for i in range(inputs.n_samples):
        temperatures = ",".join(f"{20 + v:.4f}" for v in inputs.rise_C[i])
        rows.append(f"R{inputs.run_index[i]},{(i % 150) * 60},0,{temperatures},{error[i]:.4f}")
    csv = tmp_path / "runs.csv"
    csv.write_text("\n".join(rows) + "\n")
    prepared = prepare(load_runs(csv))
    store = ModelStore(tmp_path / "store")
    for method in ("mlr", "ridge"):
        fit_and_store(prepared, method, store)
    return store.root


def test_runtime_refuses_a_model_that_a_small_bias_would_move_too_far(tmp_path: Path) -> None:
    store = fragile_store(tmp_path)
    fragile = machine(store, "mlr-error_um-all", limit_um=2.0)
    with pytest.raises(ValueError, match=r"'mlr-error_um-all', which is refused: a bias of ±0\.5"):
        load_bank(fragile)
    bank = load_bank(machine(store, "ridge-error_um-all", limit_um=2.0))
    assert "ridge-error_um-all" in bank and "mlr-error_um-all" not in bank
    # With the limit raised knowingly, the fragile model is usable again.
    assert "mlr-error_um-all" in load_bank(machine(store, "mlr-error_um-all", limit_um=500.0))


def test_vif_of_exact_combinations_is_unbounded_never_negative() -> None:
    # a, b, a + b (+ 1e-9 noise) and a − b span two directions: a plain inverse of their
    # correlation matrix gave VIFs of −1e15 … +1e15 here; t is separable, its VIF the
    # textbook 1 / (1 − R²) of t on the others.
    t = np.linspace(0, 10, 500)
    a, b = 1 - np.exp(-t / 3), 1 - np.exp(-t / 4)
    for seed in range(5):
        noise = np.random.default_rng(seed).normal(0, 1e-9, t.size)
        X = np.column_stack([a, b, a + b + noise, a - b, t])
        vif = variance_inflation(X)
        assert np.all(vif >= 1.0)
        assert np.all(np.isinf(vif[:4]))
        others = np.column_stack([np.ones(t.size), a, b])
        residual = t - others @ np.linalg.lstsq(others, t, rcond=None)[0]
        assert vif[4] == pytest.approx(np.sum((t - t.mean()) ** 2) / np.sum(residual**2))


def test_constant_and_collinear_inputs_are_named_not_given_a_figure() -> None:
    inputs, error = exact_inputs()
    zero_speed = ModelInputs(inputs.rise_C, inputs.sensors, np.zeros(inputs.n_samples))
    doubled = np.column_stack([inputs.rise_C, 2.0 * inputs.rise_C[:, 0]])
    model = make_model("mlr").fit(zero_speed, error)
    figures = assess(model, zero_speed)
    assert figures.constant == () and figures.collinear == ()
    X = np.column_stack([doubled, np.zeros(inputs.n_samples)])
    assert list(np.isinf(variance_inflation(X))) == [True, False, True, True]
    text = figures.table()
    assert "inf" not in text and "nan" not in text


def test_fit_shows_the_worst_vifs_by_default_and_every_input_behind_a_flag(
    tmp_path: Path,
) -> None:
    csv = write_runs_csv(tmp_path / "runs.csv", n_runs=4, n=200)
    runs = []
    for shown in ("short", "full"):
        out = tmp_path / f"{shown}.json"
        result = gateway_in_process(
            "fit", csv, "--store", tmp_path / shown, "--json", out, "--no-progress",
            "--collinearity", shown,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        section = result.stdout.split("conditioning:", 1)[1].split("bias of ±")[0]
        record = next(iter(json.loads(out.read_text())["conditioning"].values()))
        runs.append((section, record))
    (short, record), (full, full_record) = runs
    assert record == full_record  # the JSON holds every input either way
    terms = list(record["vif"])
    assert len(terms) > 10
    assert all(v is None or v >= 1.0 for v in record["vif"].values())
    assert len(short.strip().splitlines()) <= 4 and "--collinearity full" in short
    assert "inf" not in short
    for term in terms:
        assert any(line.split()[:1] == [term] for line in full.splitlines()), term
