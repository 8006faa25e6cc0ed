"""``python -m gateway score``: a stored model on a new recording, no refit, as the gateway runs it.

Fitted on some simulated runs (A), scored on others (B): the figures equal the
held-out error computed by hand from the stored model; an augmented model with lag
terms and a lag-ridge model give what the runtime's own classes predict, stepped
sample by sample with their lags warm across a continuous recording.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from gateway.live.bank.lag_state import EffectStates
from gateway.live.bank.model_bank import BankedAugmented
from models.analysis import augmented
from models.data.dataset import AMBIENT_COLUMN, load_runs
from models.data.features import Prepared, prepare
from models.data.references import first_rows
from models.fit.metrics import accuracy
from models.store import load_file
from tests.cli import gateway_in_process

TOLERANCE_UM = 1e-9


def simulate(path: Path, programs: list[str], seed: int, effect: str = "thermal_lag") -> Path:
    options = [item for program in programs for item in ("--program", program)]
    done = gateway_in_process(
        "simulate", "--record", path, *options, "--effect", effect, "--seed", seed
    )
    assert done.returncode == 0, done.stderr
    return path


def continuous(source: Path, path: Path) -> Path:
    """``source`` with each run's clock following on from the run before: one recording."""
    with source.open(encoding="utf-8", newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    run, time = header.index("run"), header.index("time_s")
    offset, last, current = 0.0, 0.0, body[0][run]
    for row in body:
        if row[run] != current:
            current, offset = row[run], last + 60.0
        row[time] = f"{float(row[time]) + offset:g}"
        last = float(row[time])
    with path.open("w", encoding="utf-8", newline="") as f:
        csv.writer(f).writerows([header, *body])
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("score")
    a = simulate(folder / "a.csv", ["iso230-spectrum", "const2000", "const4000"], seed=1)
    b = simulate(folder / "b.csv", ["spectrum-swapped", "const6000"], seed=2)
    return {"a": a, "b": b, "b_continuous": continuous(b, folder / "b-continuous.csv")}


def fitted(data: Path, store: Path, method: str) -> Path:
    done = gateway_in_process("fit", data, "--method", method, "--store", store, "--no-progress")
    assert done.returncode == 0, done.stderr
    (path,) = store.glob(f"{method}-*.json")
    return path


def scored(data: Path, *options: str | Path, out: Path) -> dict:
    done = gateway_in_process("score", data, *options, "--json", out)
    assert done.returncode == 0, done.stderr
    assert "no refit" in done.stdout and "pooled" in done.stdout
    return json.loads(out.read_text(encoding="utf-8"))


def by_run(prepared: Prepared, predicted: np.ndarray) -> dict[str, dict]:
    figures = {
        run_id: accuracy(prepared.error_um[rows], predicted[rows]).as_dict()
        for run_id, rows in prepared.data.run_slices()
    }
    figures["pooled"] = accuracy(prepared.error_um, predicted).as_dict()
    return figures


def assert_same(result: dict, expected: dict[str, dict]) -> None:
    got = {**result["per_run"], "pooled": result["pooled"]}
    assert set(got) == set(expected)
    for name, figures in expected.items():
        assert got[name]["n_samples"] == figures["n_samples"]
        for key in ("rmse_um", "sigma_um", "max_abs_um"):
            assert got[name][key] == pytest.approx(figures[key], abs=TOLERANCE_UM), (name, key)


def test_a_model_fitted_on_a_scores_b_as_its_held_out_error_by_hand(runs, tmp_path: Path) -> None:
    model_file = fitted(runs["a"], tmp_path / "store", "mlr")
    model, document = load_file(model_file)
    result = scored(
        runs["b"], "--model", document.model_id, "--store", tmp_path / "store", out=tmp_path / "s"
    )
    prepared = prepare(load_runs(runs["b"]), list(model.sensors_used_), "auto")
    expected = by_run(prepared, model.predict(prepared.inputs))
    assert_same(result, expected)
    assert result["refit"] is False and result["model_id"] == document.model_id
    assert set(result["per_run"]) == {"spectrum-swapped", "const6000"}
    # The same figures when the file is named instead of the id.
    again = scored(runs["b"], "--model", model_file, out=tmp_path / "again.json")
    assert again["pooled"] == result["pooled"]


def test_lag_ridge_keeps_its_lags_warm_across_a_continuous_recording(runs, tmp_path: Path):
    model_file = fitted(runs["a"], tmp_path / "store", "lag-ridge")
    model, _ = load_file(model_file)
    data = load_runs(runs["b_continuous"])
    prepared = prepare(data, list(model.sensors_used_), "auto")
    assert prepared.plan.recording_runs == (("spectrum-swapped", "const6000"),)
    result = scored(runs["b_continuous"], "--model", model_file, out=tmp_path / "s.json")
    # The batch prediction runs every lag over the whole recording: what the stream gives.
    assert_same(result, by_run(prepared, model.predict(prepared.inputs)))
    # Started cold at the second run instead, its lags give other figures.
    cold = model.predict(prepare(load_runs(runs["b"]), list(model.sensors_used_)).inputs)
    second = prepared.data.run_slices()[1][1]
    cold_rmse = accuracy(prepared.error_um[second], cold[second]).rmse_um
    assert abs(result["per_run"]["const6000"]["rmse_um"] - cold_rmse) > 1e-3


def runtime_predictions(document: dict, prepared: Prepared) -> np.ndarray:
    """The live loop's classes: one EffectStates per recording (a gateway's cold start),
    advanced each cycle with that cycle's rises and speed."""
    banked = BankedAugmented.from_document(document, AMBIENT_COLUMN)
    data, inputs = prepared.data, prepared.inputs
    starts = first_rows(prepared.plan.recording)
    out = np.empty(data.n_samples)
    states = None
    for k in range(data.n_samples):
        if states is None or starts[k] == k:
            states = EffectStates([banked], None)
        rises = dict(zip(inputs.sensors, map(float, inputs.rise_C[k]), strict=True))
        value = states.advance(float(data.time_s[k]), rises, float(data.speed_rpm[k]))
        out[k] = value[banked.model_id]
    return out


def test_an_augmented_model_gives_what_the_running_gateway_predicts(runs, tmp_path: Path):
    store = tmp_path / "store"
    done = gateway_in_process(
        "analyze", runs["a"], "--model", "mlr", "--store", store, "--no-progress"
    )
    assert done.returncode == 0, done.stderr
    (path,) = (store / augmented.FOLDER).glob("*.json")
    document = augmented.load(path)
    assert any(e["effect"] == "thermal_lag" for e in document["effects"])  # a lag term
    result = scored(
        runs["b_continuous"], "--model", document["model_id"], "--store", store, out=tmp_path / "s"
    )
    banked = BankedAugmented.from_document(document, AMBIENT_COLUMN)
    sensors = [s for s in banked.stream().sensors if s != AMBIENT_COLUMN]
    prepared = prepare(load_runs(runs["b_continuous"]), sensors, "auto")
    assert_same(result, by_run(prepared, runtime_predictions(document, prepared)))
    assert result["kind"] == "augmented"


def test_data_outside_the_training_span_are_named(runs, tmp_path: Path) -> None:
    slow = simulate(tmp_path / "slow.csv", ["const2000"], seed=3)
    model_file = fitted(slow, tmp_path / "store", "mlr")
    done = gateway_in_process("score", runs["b"], "--model", model_file, "--json", tmp_path / "o")
    assert done.returncode == 0, done.stderr
    outside = json.loads((tmp_path / "o").read_text(encoding="utf-8"))["outside_training"]
    speed = [e for e in outside if e["input"] == "speed"]
    assert speed and speed[0]["trained"][1] == pytest.approx(2000, abs=1)
    assert speed[0]["max"] > 5000
    assert "warning: outside the training data: speed:" in done.stdout
    # Another day at the same speed stays inside.
    same = simulate(tmp_path / "same.csv", ["const2000"], seed=4)
    done = gateway_in_process("score", same, "--model", model_file, "--json", tmp_path / "i")
    assert done.returncode == 0, done.stderr
    inside = json.loads((tmp_path / "i").read_text(encoding="utf-8"))["outside_training"]
    assert not [e for e in inside if e["input"] == "speed"]
    assert "outside the training data: speed" not in done.stdout


def test_bad_input_is_refused_with_one_line(runs, tmp_path: Path) -> None:
    store = tmp_path / "store"
    model_file = fitted(runs["a"], store, "mlr")
    damaged = tmp_path / "damaged.json"
    damaged.write_text(
        model_file.read_text(encoding="utf-8").replace('"rows": ', '"rows": 1', 1), "utf-8"
    )
    few = tmp_path / "few.csv"
    few.write_text("run,time_s,speed_rpm,T1,error_um\na,0,0,20,0\na,60,0,20.5,0.1\n", "utf-8")
    cases = [
        (("--model", "nope", "--store", store), f"no model of that id in {store}"),
        (("--model", "nope"), "give --store DIR"),
        (("--model", damaged), "checksum mismatch"),
        (("--model", model_file, "--target", "ch9_um"), "column 'ch9_um'"),
    ]
    for options, message in cases:
        done = gateway_in_process("score", runs["b"], *options)
        assert done.returncode == 2, (options, done.stdout)
        assert message in done.stderr and done.stderr.count("\n") == 1, done.stderr
    done = gateway_in_process("score", few, "--model", model_file)
    assert done.returncode == 2 and "few.csv" in done.stderr and "'T2'" in done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
