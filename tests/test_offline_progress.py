"""Progress bars on the offline commands that can run for minutes: ``analyze`` (its base
folds, the inputs refitted inside lag-ridge, the forward folds), ``score`` (the rows
stepped through a model and their interval widths) and ``export`` (its reads, rows and
file), shown on stderr with ``--progress`` whatever the terminal, and counting up.
``fit`` and ``replay`` have theirs in test_offline_output.py and test_replay_many_runs.py."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from gateway.offline.export import EXPORT_STEPS, export_runs
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import points_from_record, probe_point
from tests.cli import gateway, gateway_in_process
from tests.many_runs import write_campaign_csv
from tests.test_timeseries import EPOCH_S, make_records, true_error_um

RUNS = 12


def advanced(stderr: str, label: str, total: int) -> bool:
    """A bar named ``label`` was drawn at some count between 1 and ``total`` of ``total``."""
    return re.search(rf"{re.escape(label)}: .*\b[1-9]\d*/{total} ", stderr) is not None


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("campaign")
    return write_campaign_csv(folder / "campaign.csv", n_runs=RUNS, hours=(1.0, 1.5), seed=4)


def test_analyze_shows_its_folds_advance(campaign: Path) -> None:
    done = gateway("analyze", campaign, "--progress")
    assert done.returncode == 0, done.stderr
    # 12 runs, each its own recording: the base's 12 folds, the drift input refitted
    # inside lag-ridge on the same 12, and 6 forward folds (runs 7 … 12).
    assert advanced(done.stderr, "base model folds", RUNS), done.stderr
    assert advanced(done.stderr, "drift inside lag-ridge", RUNS), done.stderr
    assert advanced(done.stderr, "forward folds", RUNS // 2), done.stderr
    assert "base model folds" not in done.stdout


def test_score_shows_its_rows_advance(campaign: Path, tmp_path: Path) -> None:
    store = tmp_path / "store"
    fitted = gateway_in_process("fit", campaign, "--method", "mlr", "--store", store,
                                "--no-progress")  # fmt: skip
    assert fitted.returncode == 0, fitted.stderr
    rows = sum(1 for _ in campaign.open()) - 1
    done = gateway_in_process(
        "score", campaign, "--model", "mlr-error_um-all", "--store", store, "--progress"
    )
    assert done.returncode == 0, done.stderr
    assert advanced(done.stderr, "rows' interval widths", rows), done.stderr
    quiet = gateway_in_process(
        "score", campaign, "--model", "mlr-error_um-all", "--store", store, "--no-progress"
    )
    assert "interval widths" not in quiet.stderr


def test_export_shows_its_steps_advance(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with LocalStore(tmp_path / "series.sqlite") as store:
        for k in range(RUNS):  # 12 runs of 60 cycles, an hour apart
            records = make_records("m1", 60, start_s=3600.0 * k)
            probes = [probe_point("m1", r.time_s + 0.3, true_error_um(r), EPOCH_S) for r in records]
            store.write([p for r in records for p in points_from_record(r, EPOCH_S)])
            store.write(probes)
        result = export_runs(store, "m1", None, None, tmp_path / "m1.csv", EPOCH_S, progress=True)
    assert len(result.runs) == RUNS
    shown = capsys.readouterr().err
    for count, step in enumerate(EXPORT_STEPS, start=1):
        assert f"{count}/{len(EXPORT_STEPS)} " in shown and f"{step} done" in shown, shown
