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

from gateway.demo.monitor_phase import SENSORS, InProcessPlant
from gateway.live.proposal_monitor import MonitorSink
from models.analysis.history import History, analyse_history
from models.data.lag_terms import GAP_S, first_order_lag
from models.online.residual_monitor import MonitorParams
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
        "analyze",
        csv_path,
        "--model",
        "mlr",
        "--probe-rows",
        "--json",
        out,
        "--store",
        tmp_path / "s",
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
    done = gateway_in_process("analyze", csv_path, "--model", "mlr")
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


def test_the_grid_takes_the_speed_across_a_logging_gap_as_the_lags_of_a_file_do() -> None:
    # Cycles every 60 s, a 30-min hole (the logger was down) in which the speed went from
    # 8000 to 5000 r/min, and a 90 s sensor dropout (not a gap) with the speed steady.
    time_s = np.r_[np.arange(0, 3600, 60.0), np.arange(5400, 9000, 60.0)]
    speed = np.where(time_s < 3600, 8000.0, 5000.0)
    temps = 20 + np.linspace(0, 5, time_s.size)[:, None]
    temps[70, 0] = np.nan  # one bad reading: a 120 s step, held as before
    history = History(time_s, speed, ("T1",), temps, np.full(time_s.size, np.nan))
    grid = history.on_grid(15.0)
    gap = (grid.time_s > 3540) & (grid.time_s < 5400)
    assert np.allclose(grid.speed_rpm[gap], np.interp(grid.time_s[gap], [3540, 5400], [8000, 5000]))
    assert np.all(grid.speed_rpm[~gap & (grid.time_s <= 3540)] == 8000.0)
    assert np.all(grid.speed_rpm[grid.time_s >= 5400] == 5000.0)
    assert GAP_S >= 120.0  # the dropout's 120 s step is not a gap
    # So the grid's lag of the speed is the file's lag of it, where holding the last
    # reading across the gap (the grid's rule before) was 0.21 of the change off.
    on_file = first_order_lag(speed, time_s, np.zeros(time_s.size, int), 3600.0)
    on_grid = first_order_lag(grid.speed_rpm, grid.time_s, np.zeros(grid.n_samples, int), 3600.0)
    assert np.max(np.abs(np.interp(time_s, grid.time_s, on_grid) - on_file)) < 20.0  # r/min
    held = np.where(gap, 8000.0, grid.speed_rpm)
    held_lag = first_order_lag(held, grid.time_s, np.zeros(grid.n_samples, int), 3600.0)
    assert np.max(np.abs(np.interp(time_s, grid.time_s, held_lag) - on_file)) > 0.2 * 3000
