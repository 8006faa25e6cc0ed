"""``analyze --probe-rows``: a logged history, the error known only where the probe measured it.

The history is what the residual monitor keeps (every cycle's temperatures and
speed; probe + applied compensation at probe cycles), logged from the simulated
machine with a hidden drift the model lacks. The command must find the drift
with the lags and the time term computed on every cycle and the fit on the probe
rows only, and give the same figures as the monitor's own analysis.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gateway.demo_effect import SENSORS, InProcessPlant
from gateway.monitor import MonitorSink
from models.history_analysis import analyse_history
from models.residual_monitor import MonitorParams
from simulator.programs import production_program
from tests.cli import gateway_in_process
from tests.gateway_rig import fit_store


@pytest.fixture(scope="module")
def history(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("probe-rows")
    store = fit_store(folder)
    plant = InProcessPlant(store, production_program(seed=12, duration_s=10 * 3600.0), ("drift",))
    sink = MonitorSink("vmc", SENSORS, MonitorParams(false_alarms_per_month=1e-9), cycle_s=15.0)
    plant.sinks.append(sink)
    plant.run_for(10 * 3600.0)
    return folder, sink.history.snapshot()


def test_probe_rows_find_the_drift_like_the_monitor(history, tmp_path: Path):
    _folder, logged = history
    probes = int(logged.probe_rows.sum())
    assert 100 <= probes <= 125 and logged.n_samples >= 20 * probes
    csv_path = tmp_path / "history.csv"
    logged.write_csv(str(csv_path))
    out = tmp_path / "result.json"
    done = gateway_in_process(
        "analyze", csv_path, "--probe-rows", "--json", out, "--store", tmp_path / "s"
    )
    assert done.returncode == 0, done.stderr
    assert f"({probes} with error_um)" in done.stdout
    result = json.loads(out.read_text())
    assert result["effect"] == "drift", done.stdout
    assert result["after"]["rmse_um"] <= 0.7 * result["before"]["rmse_um"]
    assert result["before"]["n_samples"] == probes  # figures on the probe rows only
    own = analyse_history(logged.complete())
    assert own["effect"] == "drift"
    assert np.isclose(own["before"]["rmse_um"], result["before"]["rmse_um"], rtol=1e-3)
    assert np.isclose(own["after"]["rmse_um"], result["after"]["rmse_um"], rtol=1e-3)
    assert list((tmp_path / "s" / "augmented").glob("*.json"))


def test_without_the_option_the_rows_between_probes_are_skipped(history, tmp_path: Path):
    _, logged = history
    csv_path = tmp_path / "history.csv"
    logged.write_csv(str(csv_path))
    done = gateway_in_process("analyze", csv_path)
    skipped = logged.n_samples - int(logged.probe_rows.sum())
    assert f"skipped {skipped} row(s)" in done.stdout + done.stderr


def test_probe_rows_refuse_a_file_without_enough_probes(history, tmp_path: Path):
    _, logged = history
    rows = logged.complete()
    error = np.full(rows.n_samples, np.nan)
    error[:: rows.n_samples // 5] = 1.0
    from dataclasses import replace

    replace(rows, error_um=error).write_csv(str(tmp_path / "few.csv"))
    done = gateway_in_process("analyze", tmp_path / "few.csv", "--probe-rows")
    assert done.returncode == 2
    assert "expected at least 10" in done.stderr and "Traceback" not in done.stderr


def test_probe_rows_still_refuse_an_absurd_target_value(history, tmp_path: Path):
    _, logged = history
    csv_path = tmp_path / "history.csv"
    logged.write_csv(str(csv_path))
    lines = csv_path.read_text().splitlines()
    probe_line = next(i for i, line in enumerate(lines[1:], start=1) if not line.endswith(","))
    cells = lines[probe_line].split(",")
    cells[-1] = "1e308"
    lines[probe_line] = ",".join(cells)
    csv_path.write_text("\n".join(lines) + "\n")
    done = gateway_in_process("analyze", csv_path, "--probe-rows")
    assert done.returncode == 2
    assert f"history.csv:{probe_line + 1}: column 'error_um'" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr
