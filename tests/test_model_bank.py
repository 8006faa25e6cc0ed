"""The model bank holds one target: a store mixing targets or units is refused at load."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from gateway.live.bank.model_bank import ModelBank
from models.data.dataset import load_runs
from models.data.features import prepare
from models.fit.workflow import fit_sensor_fallbacks
from models.store import ModelStore
from tests.cli import gateway_in_process
from tests.synthetic import write_runs_csv
from tests.test_config import GOOD, write_config
from tests.test_store import resealed


def two_target_csv(path: Path) -> Path:
    """The synthetic runs with a second probe channel, ``other_um``, another mix of rises."""
    write_runs_csv(path)
    lines = path.read_text(encoding="utf-8").splitlines()
    out = [lines[0] + ",other_um"]
    header = lines[0].split(",")
    t3, t5 = header.index("T3"), header.index("T5")
    first: dict[str, list[float]] = {}
    for line in lines[1:]:
        cells = line.split(",")
        start = first.setdefault(cells[0], [float(cells[t3]), float(cells[t5])])
        other = 3.0 * (float(cells[t3]) - start[0]) + 1.5 * (float(cells[t5]) - start[1])
        out.append(f"{line},{other:.6g}")
    path.write_text("\n".join(out) + "\n", encoding="utf-8")
    return path


def fit(data: Path, store: Path, target: str) -> None:
    """The CLI's model on every sensor, then the library's sensor fallbacks, into one store."""
    result = gateway_in_process(
        "fit", data, "--method", "mlr", "--store", store, "--target", target
    )
    assert result.returncode == 0, result.stderr
    fit_sensor_fallbacks(prepare(load_runs(data, target=target)), "mlr", ModelStore(store))


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return two_target_csv(tmp_path_factory.mktemp("data") / "runs.csv")


@pytest.fixture(scope="module")
def one_target_store(tmp_path_factory: pytest.TempPathFactory, data: Path) -> Path:
    """error_um models only: all seven sensors, and one without each sensor."""
    store = tmp_path_factory.mktemp("one") / "models"
    fit(data, store, "error_um")
    return store


def test_a_store_of_one_target_loads_and_falls_back_within_it(
    tmp_path: Path, one_target_store: Path
) -> None:
    bank = ModelBank.from_store(one_target_store)
    assert len(bank.models) == 8
    assert str(bank.target) == "error_um (µm)"
    every = {f"T{i}" for i in range(1, 8)}
    preferred = bank.usable("mlr-error_um-all", every)
    assert preferred is not None and preferred.model_id == "mlr-error_um-all"
    fallback = bank.usable("mlr-error_um-all", every - {"T1"})
    assert fallback is not None and fallback.model_id == "mlr-error_um-all-without-T1"
    assert fallback.target == preferred.target
    result = gateway_in_process(
        "check-config", "--config", write_config(tmp_path, one_target_store, GOOD)
    )
    assert result.returncode == 0, result.stderr
    assert "8 models in" in result.stdout and "(target error_um (µm))" in result.stdout


def test_a_store_mixing_targets_is_refused_naming_models_and_targets(
    tmp_path: Path, data: Path, one_target_store: Path
) -> None:
    store = tmp_path / "models"
    shutil.copytree(one_target_store, store)
    fit(data, store, "other_um")
    other_ids = sorted(p.stem for p in store.glob("*other_um*.json"))
    assert len(other_ids) == 8
    with pytest.raises(ValueError) as caught:
        ModelBank.from_store(store)
    message = str(caught.value)
    assert message.startswith(f"model store {store}: its models predict different targets")
    assert f"other_um (µm): {', '.join(other_ids)}" in message
    assert "error_um (µm): mlr-error_um-all, mlr-error_um-all-without-T1," in message
    result = gateway_in_process("check-config", "--config", write_config(tmp_path, store, GOOD))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1, result.stderr
    assert "predict different targets" in result.stderr and other_ids[0] in result.stderr
    assert "Traceback" not in result.stderr


def test_a_store_mixing_units_of_one_target_is_refused(
    tmp_path: Path, one_target_store: Path
) -> None:
    store = tmp_path / "models"
    shutil.copytree(one_target_store, store)
    document = json.loads((store / "mlr-error_um-all.json").read_text(encoding="utf-8"))
    document["model_id"] = "mlr-error_um-all-in-mm"
    document["target"]["unit"] = "mm"
    document = resealed(document, store)  # a consistent file, not a damaged one
    (store / "mlr-error_um-all-in-mm.json").write_text(json.dumps(document), encoding="utf-8")
    with pytest.raises(ValueError) as caught:
        ModelBank.from_store(store)
    message = str(caught.value)
    assert "error_um (mm): mlr-error_um-all-in-mm" in message
    assert "error_um (µm): mlr-error_um-all" in message
