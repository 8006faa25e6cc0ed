"""Model store: fit → save → load → identical predictions; damaged files refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models import signing
from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.registry import METHODS, make_model
from models.store import ModelStore, StoreError, _checksum, canonical_bytes, load_file
from tests.synthetic import stored_document, write_runs_csv


@pytest.fixture(scope="module")
def prepared(tmp_path_factory: pytest.TempPathFactory):
    path = write_runs_csv(tmp_path_factory.mktemp("data") / "runs.csv")
    return prepare(load_runs(path))


def save_fitted(prepared, store: ModelStore, method: str) -> tuple[object, dict, Path]:
    model = make_model(method).fit(prepared.inputs, prepared.error_um)
    document = stored_document(prepared, model, f"{method}-error_um-all")
    return model, document, store.save(document)


@pytest.mark.parametrize("method", sorted(METHODS))
def test_round_trip_gives_identical_predictions(prepared, tmp_path: Path, method: str) -> None:
    store = ModelStore(tmp_path)
    model, document, path = save_fitted(prepared, store, method)
    loaded, stored = store.load(document["model_id"])
    assert type(loaded) is type(model)
    assert np.array_equal(loaded.predict(prepared.inputs), model.predict(prepared.inputs))
    assert stored.method == method and stored.regime == "all"
    assert stored.training_data.rows == prepared.inputs.n_samples
    assert stored.training_data.runs == ["R1", "R2", "R3", "R4"]
    assert stored.reference["policy"] == "auto"
    assert set(model.sensors_used_) <= set(stored.inputs)
    assert all(unit for unit in stored.inputs.values())
    assert stored.target["unit"] == "µm"
    assert stored.created_utc.endswith("Z")
    assert store.ids() == [document["model_id"]]
    assert path.read_text().count("\n") > 10  # human-readable, indented JSON


def test_same_data_same_fingerprint_other_data_other(prepared, tmp_path: Path) -> None:
    _, first, _ = save_fitted(prepared, ModelStore(tmp_path / "a"), "mlr")
    _, second, _ = save_fitted(prepared, ModelStore(tmp_path / "b"), "mlr")
    assert first["training_data"]["data_sha256"] == second["training_data"]["data_sha256"]
    shifted = prepared.take(np.arange(prepared.inputs.n_samples - 1))
    _, third, _ = save_fitted(shifted, ModelStore(tmp_path / "c"), "mlr")
    assert third["training_data"]["data_sha256"] != first["training_data"]["data_sha256"]


def rewrite(path: Path, change, fix_checksum: bool) -> None:
    """``change`` the file; ``fix_checksum``: its checksum and signature made again, as a
    holder of the key would write it (the checks after the signature's are tested)."""
    document = json.loads(path.read_text())
    change(document)
    if fix_checksum:
        document = resealed(document, path.parent)
    path.write_text(json.dumps(document))


def resealed(document: dict, store_dir: Path) -> dict:
    """``document`` with its checksum and its signature (the store's key) made again."""
    document = {k: v for k, v in document.items() if k != signing.FIELD}
    document["sha256"] = _checksum(document)
    key = signing.key_for_store(store_dir)
    return signing.sign(document, key, canonical_bytes(document))


def refusal(path: Path) -> str:
    with pytest.raises(StoreError) as caught:
        load_file(path)
    assert str(path) in str(caught.value)
    return str(caught.value)


def test_edited_number_fails_the_checksum(prepared, tmp_path: Path) -> None:
    _, _, path = save_fitted(prepared, ModelStore(tmp_path), "mlr")
    rewrite(path, lambda d: d["params"].__setitem__("intercept_um", 99.0), fix_checksum=False)
    assert "checksum mismatch" in refusal(path)


def test_numbers_that_do_not_reproduce_the_probe_are_refused(prepared, tmp_path: Path) -> None:
    _, _, path = save_fitted(prepared, ModelStore(tmp_path), "mlr")
    rewrite(
        path, lambda d: d["params"]["coefficients_um_per_C"].__setitem__(0, 1.0), fix_checksum=True
    )
    assert "does not reproduce its saved probe predictions" in refusal(path)


def test_truncated_file(prepared, tmp_path: Path) -> None:
    _, _, path = save_fitted(prepared, ModelStore(tmp_path), "pca-quadratic")
    path.write_text(path.read_text()[:200])
    assert "not a readable JSON model file" in refusal(path)


def test_newer_format_version(prepared, tmp_path: Path) -> None:
    _, _, path = save_fitted(prepared, ModelStore(tmp_path), "mlr")
    rewrite(path, lambda d: d.__setitem__("format_version", 2), fix_checksum=True)
    assert "format_version 2 is not supported" in refusal(path)


def test_not_a_model_file(tmp_path: Path) -> None:
    path = tmp_path / "x.json"
    path.write_text('{"hello": 1}')
    assert "not a model file" in refusal(path)


def test_missing_field_is_named(prepared, tmp_path: Path) -> None:
    _, _, path = save_fitted(prepared, ModelStore(tmp_path), "mlr")
    rewrite(path, lambda d: d.pop("training_data"), fix_checksum=True)
    assert "field 'training_data'" in refusal(path)


def test_unknown_method(prepared, tmp_path: Path) -> None:
    _, _, path = save_fitted(prepared, ModelStore(tmp_path), "mlr")
    rewrite(path, lambda d: d.__setitem__("method", "neural-net"), fix_checksum=True)
    assert "unknown method 'neural-net'" in refusal(path)


def test_params_of_the_wrong_shape(prepared, tmp_path: Path) -> None:
    _, _, path = save_fitted(prepared, ModelStore(tmp_path), "mlr")
    rewrite(path, lambda d: d["params"]["coefficients_um_per_C"].pop(), fix_checksum=True)
    assert "fitted numbers do not fit method 'mlr'" in refusal(path)


def test_save_leaves_no_temporary_files(prepared, tmp_path: Path) -> None:
    save_fitted(prepared, ModelStore(tmp_path), "mlr")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mlr-error_um-all.json"]
