"""Bad measured data through the real command line: one located message, exit 2, no model.

Every ``tests/cases/data/NAME.csv`` is a file ``fit`` must refuse; ``NAME.expected``
holds the one line it must print after ``error: `` (``{file}`` stands for the
path given). The folder is walked, so a new case is a new pair of files.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from models.base import ModelInputs
from models.data.dataset import load_runs
from models.data.features import prepare
from models.fit.workflow import fit_and_store
from models.store import ModelStore, StoreError
from tests.cli import gateway, gateway_in_process
from tests.synthetic import stored_document, write_runs_csv

CASES = Path(__file__).resolve().parent / "cases" / "data"
CASE_NAMES = sorted(p.stem for p in CASES.glob("*.csv"))
# analyze reads through the same loader; these cases prove it refuses just as fit does.
ANALYZE_CASES = (
    "temperature_1e308",
    "latin1_byte",
    "nul_byte",
    "too_few_fields",
    "text_cell",
    "one_short_run",
)


def expected_message(name: str, path: Path) -> str:
    text = (CASES / f"{name}.expected").read_text(encoding="utf-8").strip()
    return "error: " + text.replace("{file}", str(path))


def test_the_case_folder_is_complete() -> None:
    assert len(CASE_NAMES) >= 25
    for name in CASE_NAMES:
        assert (CASES / f"{name}.expected").is_file(), name
    assert set(ANALYZE_CASES) <= set(CASE_NAMES)


@pytest.mark.parametrize(
    ("command", "name"),
    [("fit", name) for name in CASE_NAMES] + [("analyze", name) for name in ANALYZE_CASES],
)
def test_bad_file_is_refused_with_one_located_message(
    command: str, name: str, tmp_path: Path
) -> None:
    path = CASES / f"{name}.csv"
    store = tmp_path / "store"
    # One case of each command as a real process; the table in this process (tests/cli.py).
    run = gateway if name == ANALYZE_CASES[0] else gateway_in_process
    result = run(command, path, "--store", store, "--no-progress")
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines() == [expected_message(name, path)]
    assert "Traceback" not in result.stdout + result.stderr
    assert not store.exists() or not any(store.rglob("*.json"))


def test_copied_sensor_columns_and_a_spindle_at_rest_are_fitted_with_a_located_warning(
    tmp_path: Path,
) -> None:
    """Sensor columns equal on every row (one reading exported to several columns) and a
    speed of 0 on every row still make a model, with one warning each naming the file,
    the columns and the rows."""
    good = write_runs_csv(tmp_path / "good.csv", seed=3).read_text(encoding="utf-8")
    header, *rows = [line.split(",") for line in good.splitlines()]
    speed, first, error = header.index("speed_rpm"), header.index("T1"), header.index("error_um")
    copied = [[*r[:first], *[r[first]] * (error - first), *r[error:]] for r in rows]
    at_rest = [[*r[:speed], "0", *r[speed + 1 :]] for r in rows]
    lines = f"lines 2–{len(rows) + 1}"
    for name, table, expected in (
        (
            "copied",
            copied,
            f"every sensor column 'T1', 'T2', 'T3', 'T4', 'T5', 'T6', 'T7' "
            f"read the same on every row ({lines})",
        ),
        ("at_rest", at_rest, f"column 'speed_rpm' is 0 r/min on every row ({lines})"),
    ):
        path = tmp_path / f"{name}.csv"
        path.write_text("\n".join(",".join(r) for r in [header, *table]) + "\n", "utf-8")
        store = tmp_path / f"store-{name}"
        result = gateway_in_process(
            "fit", path, "--method", "mlr", "--store", store, "--no-progress"
        )
        assert result.returncode == 0, result.stderr
        warnings = [line for line in result.stderr.splitlines() if line.startswith("warning: ")]
        assert warnings[0].startswith(f"warning: {path}:1: {expected}: "), warnings
        assert len([w for w in warnings if str(path) in w and "every row" in w]) == 1
        assert any(store.glob("*.json"))
    result = gateway_in_process(
        "fit", write_runs_csv(tmp_path / "plain.csv", seed=3), "--store", tmp_path / "s"
    )
    assert "every row" not in result.stderr


def test_a_utf8_byte_order_mark_is_accepted(tmp_path: Path) -> None:
    plain = write_runs_csv(tmp_path / "plain.csv", seed=3)
    marked = tmp_path / "marked.csv"
    marked.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    results = {}
    for path in (plain, marked):
        out = tmp_path / f"{path.stem}.json"
        store = tmp_path / f"store-{path.stem}"
        result = gateway_in_process(
            "fit", path, "--method", "mlr", "--store", store, "--json", out, "--no-progress"
        )
        assert result.returncode == 0, result.stderr
        results[path.stem] = json.loads(out.read_text(encoding="utf-8"))["validations"]
    assert results["marked"] == results["plain"]
    data = load_runs(marked)
    assert data.run_ids == load_runs(plain).run_ids and "run" not in data.labels


def test_a_bad_cell_in_a_column_the_command_does_not_need_is_noted_not_fatal(
    tmp_path: Path,
) -> None:
    source = (CASES / "temperature_1e308.csv").read_text(encoding="utf-8")
    path = tmp_path / "runs.csv"
    path.write_text(source, encoding="utf-8")
    result = gateway_in_process(
        "fit",
        path,
        "--method",
        "mlr",
        "--sensors",
        "T2",
        "--store",
        tmp_path / "s",
        "--no-progress",
    )
    assert result.returncode == 0, result.stderr
    assert (
        f"note: {path}: column 'T1' is not used as a signal: line 4: expected a temperature "
        "in °C from -60 to 400, found 1e+308"
    ) in result.stderr.splitlines()
    assert "T1" not in load_runs(path, sensors=["T2"]).numeric


def _huge_prepared(tmp_path: Path):
    """A data set built in code, past the loader (as a script might): one absurd cell."""
    good = prepare(load_runs(write_runs_csv(tmp_path / "runs.csv", seed=4)))
    data = good.data
    numeric = dict(data.numeric)
    numeric["T1"] = data.numeric["T1"].copy()
    numeric["T1"][len(numeric["T1"]) // 2] = 1e308  # as the file held
    return prepare(dataclasses.replace(data, numeric=numeric))


def test_a_model_whose_figures_are_not_finite_is_never_saved(tmp_path: Path) -> None:
    prepared = _huge_prepared(tmp_path)
    store = ModelStore(tmp_path / "store")
    with pytest.raises(StoreError) as caught, np.errstate(over="ignore", invalid="ignore"):
        fit_and_store(prepared, "mlr", store)
    message = str(caught.value)
    assert message.startswith("model 'mlr-error_um-all' not saved: ")
    assert "is inf" in message or "is nan" in message
    assert not store.root.exists() or list(store.root.iterdir()) == []


def test_the_store_refuses_a_non_finite_number_anywhere_in_a_document(tmp_path: Path) -> None:
    prepared = prepare(load_runs(write_runs_csv(tmp_path / "runs.csv", seed=5)))
    from models.estimators.registry import make_model

    model = make_model("mlr").fit(prepared.inputs, prepared.error_um)
    store = ModelStore(tmp_path / "store")

    def document(validation: dict) -> dict:
        return stored_document(prepared, model, "m", source_file="runs.csv", validation=validation)

    for bad, where in (
        ({"pooled": {"rmse_um": math.inf}}, "validation.pooled.rmse_um is inf"),
        ({"per_fold": {"K1": [1.0, math.nan]}}, "validation.per_fold.K1[1] is nan"),
    ):
        with pytest.raises(StoreError, match=where.replace("[", r"\[").replace("]", r"\]")):
            store.save(document(bad))
    assert not store.root.exists() or list(store.root.iterdir()) == []
    saved = store.save(document({"pooled": {"rmse_um": 0.5}}))
    assert store.load("m")[1].validation["pooled"]["rmse_um"] == 0.5 and saved.is_file()


def test_no_stored_model_has_a_non_finite_number(tmp_path: Path) -> None:
    """Whatever fit saves passes a strict JSON parser (no NaN, Infinity)."""
    path = write_runs_csv(tmp_path / "runs.csv", seed=6)
    store = tmp_path / "store"
    assert (
        gateway_in_process(
            "fit", path, "--method", "mlr", "--store", store, "--no-progress"
        ).returncode
        == 0
    )
    files = list(store.glob("*.json"))
    assert files

    def refuse(token: str) -> float:
        raise AssertionError(f"non-finite number {token} in a stored model")

    for file in files:
        document = json.loads(file.read_text(encoding="utf-8"), parse_constant=refuse)
        assert np.isfinite(document["validation"]["pooled"]["rmse_um"])


def test_a_directory_named_like_a_file_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "runs.csv"
    shutil.copytree(CASES / "directory.csv", folder)
    result = gateway_in_process("analyze", folder, "--no-progress")
    assert result.returncode == 2
    assert result.stderr.splitlines() == [
        f"error: {folder}: is a directory; a measured-run CSV file was expected"
    ]


def test_inputs_stay_what_the_loader_read(tmp_path: Path) -> None:
    """The loader's arrays reach the model unchanged (rises of the values read)."""
    path = write_runs_csv(tmp_path / "runs.csv", seed=7)
    prepared = prepare(load_runs(path))
    assert isinstance(prepared.inputs, ModelInputs)
    assert prepared.inputs.rise_C.dtype == np.float64
    assert np.all(np.isfinite(prepared.inputs.rise_C))


def test_export_leaves_implausible_logged_values_empty(tmp_path: Path) -> None:
    """A logged 1e308 °C or an infinite probe value never reaches the exported file."""
    from gateway.offline.export import export_runs
    from gateway.outputs.local_store import LocalStore
    from gateway.outputs.points import Point, points_from_record, probe_point
    from tests.test_timeseries import EPOCH_S, make_records, true_error_um

    records = make_records("m1", 40)
    points = [p for r in records for p in points_from_record(r, EPOCH_S)]
    broken = next(i for i, p in enumerate(points) if p.tags.get("sensor") == "T1" and p.time_ns > 0)
    points[broken] = Point(points[broken].measurement, points[broken].tags, {"value_C": 1e308},
                           points[broken].time_ns)  # fmt: skip
    probes = [probe_point("m1", r.time_s + 0.3, true_error_um(r), EPOCH_S) for r in records]
    probes[5] = Point(probes[5].measurement, probes[5].tags, {"error_um": math.inf},
                      probes[5].time_ns)  # fmt: skip
    out = tmp_path / "export.csv"
    with LocalStore(tmp_path / "series.sqlite") as store:
        store.write(points + probes)
        result = export_runs(store, "m1", None, None, out, epoch_s=EPOCH_S)
    assert result.implausible_values == 2
    assert "1e+308" not in out.read_text() and "inf" not in out.read_text()
    data = load_runs(out)
    assert data.n_samples == 40 - 2  # the 1e308 row skipped (empty T1), the inf probe row left out
    assert np.all(np.abs(data.column("T1")) < 400)
