"""What the offline commands print: notes on one stream, errors that name what the
user gave, progress over many runs, nothing said about a speed that was not recorded,
an outlier run named, and ``fit`` and ``analyze`` agreeing on the same base."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from models.analysis.search import analyze
from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.registry import make_model
from models.fit.crossval import cross_validate
from tests.cli import gateway_in_process
from tests.many_runs import write_campaign_csv
from tests.synthetic import write_runs_csv
from tests.test_analysis_agreement import _result


def with_an_empty_cell(path: Path) -> Path:
    """``path`` with one temperature cell of its fifth data row left empty."""
    lines = path.read_text(encoding="utf-8").splitlines()
    cells = lines[5].split(",")
    cells[4] = ""
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def holed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("holed")
    return with_an_empty_cell(write_runs_csv(folder / "runs.csv", n_runs=4, n=120))


@pytest.fixture(scope="module")
def stored(holed: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    store = tmp_path_factory.mktemp("store")
    done = gateway_in_process("fit", holed, "--method", "mlr", "--store", store, "--no-progress")
    assert done.returncode == 0, done.stderr
    return store


@pytest.mark.parametrize("command", ["fit", "analyze", "score", "replay"])
def test_the_skipped_rows_note_goes_to_stderr_in_every_command(
    command: str, holed: Path, stored: Path, tmp_path: Path
) -> None:
    options = {
        "fit": ["--method", "mlr", "--store", tmp_path, "--no-progress"],
        "analyze": ["--model", "mlr", "--no-progress"],
        "score": ["--model", "mlr-error_um-all", "--store", stored],
        "replay": ["--model", "mlr", "--base", "declared", "--no-progress"],
    }[command]
    done = gateway_in_process(command, holed, *options)
    assert done.returncode == 0, done.stderr
    assert re.search(r"^note: .*skipped 1 row", done.stderr, re.MULTILINE), done.stderr
    assert "note:" not in done.stdout and "skipped 1 row" not in done.stdout


def test_score_names_the_models_sensors_when_the_file_lacks_them(
    stored: Path, tmp_path: Path
) -> None:
    source = write_runs_csv(tmp_path / "full.csv", n_runs=2, n=60)
    lines = source.read_text(encoding="utf-8").splitlines()
    fewer = tmp_path / "fewer.csv"
    keep = [i for i, name in enumerate(lines[0].split(",")) if name not in ("T6", "T7")]
    fewer.write_text(
        "\n".join(",".join(line.split(",")[i] for i in keep) for line in lines) + "\n",
        encoding="utf-8",
    )
    done = gateway_in_process("score", fewer, "--model", "mlr-error_um-all", "--store", stored)
    assert done.returncode != 0
    assert "--sensors" not in done.stderr
    assert f"{fewer}:1: column 'T6': the model mlr-error_um-all reads sensor(s) T6, T7" in (
        done.stderr
    )


def test_fit_shows_progress_while_its_folds_run_in_parallel(tmp_path: Path) -> None:
    csv = write_campaign_csv(tmp_path / "campaign.csv", n_runs=12, hours=(1.0, 1.5))
    done = gateway_in_process(
        "fit", csv, "--method", "mlr", "--store", tmp_path / "store", "--progress"
    )
    assert done.returncode == 0, done.stderr
    assert re.search(r"held-out folds: .*\b[1-9]\d*/12 ", done.stderr), done.stderr


def test_nothing_is_said_about_speed_on_a_recording_without_speed(tmp_path: Path) -> None:
    csv = tmp_path / "temperatures_only.csv"
    write_campaign_csv(csv, n_runs=4, hours=(2.0, 3.0), speed=False)
    out = tmp_path / "fit.json"
    done = gateway_in_process(
        "fit", csv, "--store", tmp_path / "store", "--json", out, "--no-progress"
    )
    assert done.returncode == 0, done.stderr
    assert "speed" not in done.stdout and "n_krpm" not in done.stdout
    (model,) = json.loads(out.read_text())["saved"].values()
    params = json.loads(Path(model).read_text())["params"]
    assert params["speed_powers"] == []
    assert not any("n_krpm" in term for term in params["terms"])


@pytest.mark.parametrize("method", ["lag-ridge", "ridge", "mlr"])
def test_fit_and_analyze_report_the_same_figure_for_the_same_base(
    method: str, tmp_path: Path
) -> None:
    csv = write_runs_csv(tmp_path / "runs.csv", n_runs=4, n=200, seed=5)
    prepared = prepare(load_runs(csv)).without_sensor_readings()
    validated = cross_validate(lambda: make_model(method), prepared)
    result, _, _ = analyze(prepared, method)
    for key in ("rmse_um", "sigma_um", "max_abs_um"):
        fitted = validated.pooled.as_dict()[key]
        assert result.before.as_dict()[key] == pytest.approx(fitted, abs=1e-9), key
    # The commands print and write the same figure (analyze's JSON to 4 decimals).
    fitted_json, analysed_json = tmp_path / "fit.json", tmp_path / "analyze.json"
    done = gateway_in_process(
        "fit", csv, "--method", method, "--store", tmp_path / "s", "--json", fitted_json,
        "--no-progress",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = gateway_in_process(
        "analyze", csv, "--model", method, "--json", analysed_json, "--no-progress"
    )
    assert done.returncode == 0, done.stderr
    (validation,) = json.loads(fitted_json.read_text())["validations"].values()
    before = json.loads(analysed_json.read_text())["before"]
    assert before["rmse_um"] == round(validation["pooled"]["rmse_um"], 4)


def test_one_run_far_above_its_share_of_the_error_is_named_an_outlier() -> None:
    # 43 runs; one with 6 times the others' residual holds 36 / (42 + 36) = 46 % of the
    # squared error (not the 50 % of a dominant run), 20 times its 2.3 % of the rows.
    rmse = {f"day{k:02d}": 1.0 for k in range(1, 44)}
    rmse["day17"] = 6.0
    result = _result(rmse, "thermal_lag", tolerance_um=0.5)
    assert [step.action for step in result.next_steps] == ["promote", "check_run"]
    assert "check run day17" in result.next_step_text
    assert "spread over the runs" not in result.next_step_text
    assert result.as_dict()["outlier_run"] == "day17"
    # Even runs: the error is spread over them, and a sensor is what is missing.
    even = _result({f"day{k:02d}": 1.0 for k in range(1, 44)}, "thermal_lag", tolerance_um=0.5)
    assert [step.action for step in even.next_steps] == ["promote", "add_sensor"]
    assert even.outlier_run is None and even.as_dict()["outlier_run"] is None
