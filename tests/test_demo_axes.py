"""The demo per axis: its machine configuration and its table of the error at the tool."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gateway.demo.axis_table import axis_table
from gateway.demo.compensate import axis_macros, axis_targets, machine_config, write_trace
from simulator.closed_loop import Trace, error_figures
from simulator.machine import SimulatedMachine
from simulator.params import load_params
from simulator.programs import program_by_name

TRANSMITTERS = [
    {
        "name": "bus1",
        "tcp": {"host": "127.0.0.1", "port": 1502},
        "devices": [{"device_id": 1, "channels": ["T1"]}],
    }
]
CNC = {"opcua": {"endpoint": "opc.tcp://127.0.0.1:4840", "timeout_s": 2.0}}


def perfect_x_trace(hours: float = 4.0) -> Trace:
    """The demo's trace of a machine whose X macro holds X's growth exactly (Z, Y at 0)."""
    machine = SimulatedMachine(load_params(), program_by_name("production-7"), seed=3)
    trace = Trace()
    x_macro = machine.params.axes["X"].compensation.macro
    for k in range(1, round(hours * 3600 / 60.0)):
        machine.advance_to(60.0 * k)
        machine.write_macro(x_macro, machine.axis_growth_um("X") / 1000.0)
        trace.time_s.append(machine.time_s)
        trace.uncompensated_um.append(machine.growth_um())
        trace.compensated_um.append(machine.true_error_um())
        for axis in machine.axis_names:
            without, with_ = trace.axes_um.setdefault(axis, ([], []))
            without.append(machine.axis_growth_um(axis))
            with_.append(machine.axis_true_error_um(axis))
        trace.records.append(None)
    return trace


def test_every_axis_has_its_figures_and_only_the_compensated_one_gains() -> None:
    trace = perfect_x_trace()
    figures = trace.axis_summary()
    assert list(figures) == ["Z", "X", "Y"]
    assert figures["Z"] == {k: v for k, v in trace.summary().items() if k != "cycles"}
    x, y = figures["X"], figures["Y"]
    assert x["uncompensated_rmse_um"] > 3.0 and x["uncompensated_peak_um"] > 8.0
    assert x["compensated_rmse_um"] < 1e-9 and x["reduction_pct"] == pytest.approx(100.0)
    assert y["compensated_rmse_um"] == y["uncompensated_rmse_um"] > 1.0
    without = np.asarray(trace.axes_um["X"][0])
    assert x["uncompensated_rmse_um"] == pytest.approx(float(np.sqrt(np.mean(without**2))))
    assert x["uncompensated_peak_um"] == float(np.max(np.abs(without)))


def test_the_table_shows_each_axis_without_and_with_compensation() -> None:
    figures = {
        "Z": error_figures([3.0, -4.0], [0.3, -0.4]),
        "X": error_figures([1.0, 2.0], [1.0, 2.0]),
    }
    lines = axis_table(figures, compensated={"Z"})
    assert lines[0] == axis_table({}, ())[0]
    assert (
        " ".join(lines[0].split()) == "axis RMS without RMS with max without max with RMS reduced"
    )
    z, x = lines[1].split(), lines[2].split()
    assert z == ["Z", "3.54", "0.35", "4.00", "0.40", "90.0%"]
    assert x == ["X", "1.58", "1.58", "2.00", "2.00", "not", "compensated"]


def test_the_trace_file_has_each_axis_columns(tmp_path: Path) -> None:
    trace = perfect_x_trace(hours=1.0)

    class Record:
        speed_rpm, regime, model_id, predicted_um, applied_um = 0.0, "variable", "", None, 0.0
        write_status = "ok"

    trace.records = [Record()] * len(trace.time_s)
    write_trace(tmp_path / "trace.csv", trace)
    lines = (tmp_path / "trace.csv").read_text(encoding="utf-8").splitlines()
    header = lines[0].split(",")
    assert header[-4:] == [
        "uncompensated_x_um",
        "compensated_x_um",
        "uncompensated_y_um",
        "compensated_y_um",
    ]
    last = lines[-1].split(",")
    assert float(last[header.index("compensated_x_um")]) == 0.0
    assert float(last[header.index("uncompensated_x_um")]) == round(trace.axes_um["X"][0][-1], 2)


def test_the_multi_axis_demo_machine_writes_each_axis_to_the_simulators_macro() -> None:
    machine = machine_config(
        Path("models"), transmitters=TRANSMITTERS, cnc=CNC, cycle_s=15.0, axes=("Z", "X", "Y")
    )
    axes = machine.compensation.axes
    assert axes is not None and list(axes) == ["Z", "X", "Y"]
    assert {a: s.macro for a, s in axes.items()} == axis_macros() == {"Z": 500, "X": 502, "Y": 504}
    assert {a: s.target for a, s in axes.items()} == axis_targets()
    assert axes["X"].models == {"variable": "mlr-x_um-variable", "constant": "mlr-x_um-constant"}
    assert axes["Y"].fallback_model == "mlr-y_um-all"
    single = machine_config(Path("models"), transmitters=TRANSMITTERS, cnc=CNC, cycle_s=15.0)
    assert single.compensation.axes is None and single.compensation.macro == 500
    assert single.models.regimes.fallback_model == "mlr-error_um-all"
