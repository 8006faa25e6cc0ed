"""The simulated machine: reproducible recordings, plausible physics, visible hidden effects."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.data.dataset import load_runs
from models.data.references import plan_references
from simulator.faults import SensorFault
from simulator.link import ChannelStatus
from simulator.machine import SimulatedMachine
from simulator.params import load_params
from simulator.programs import SpeedProgram, load_programs, production_program, program_by_name
from simulator.record import REST_BEFORE_S, record
from tests.cli import gateway, gateway_in_process

ROOT = Path(__file__).resolve().parent.parent
PARAMS = load_params()
PROGRAMS = load_programs()


def table(program: str, effect: str = "none", seed: int = 1) -> dict[str, np.ndarray]:
    """One recorded run as columns."""
    rec = record(PARAMS, [PROGRAMS[program]], [effect], seed=seed)
    columns = list(zip(*rec.rows, strict=True))
    return {
        name: np.array(col, dtype=float)
        for name, col in zip(rec.header[1:], columns[1:], strict=True)
    }


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path: Path) -> None:
    paths = [tmp_path / f"{name}.csv" for name in ("a", "b", "c")]
    for path, seed in zip(paths, (7, 7, 8), strict=True):
        result = gateway("simulate", "--record", path, "--seed", seed, "--effect", "cooler")
        assert result.returncode == 0, result.stderr
    assert paths[0].read_bytes() == paths[1].read_bytes()
    assert paths[0].read_bytes() != paths[2].read_bytes()


def test_recording_passes_the_loader_and_each_run_starts_cold(tmp_path: Path) -> None:
    path = tmp_path / "sim.csv"
    result = gateway_in_process(
        "simulate", "--record", path, "--program", "const4000", "--program", "iso230-spectrum"
    )
    assert result.returncode == 0, result.stderr
    data = load_runs(path)
    assert data.run_ids == ("const4000", "iso230-spectrum")
    assert data.sensors == tuple(f"T{i}" for i in range(1, 10))
    assert data.ambient_C is not None
    assert plan_references(data).recording_runs == (("const4000",), ("iso230-spectrum",))
    first = data.temperatures()[0]
    assert np.all(np.abs(first - PARAMS.ambient_C) < 1.0)  # cold start at room temperature


def growth_curve(program: SpeedProgram) -> tuple[np.ndarray, np.ndarray]:
    machine = SimulatedMachine(PARAMS, program)
    times = np.arange(0, program.duration_s + 1, 60.0)
    growth = []
    for t in times:
        machine.advance_to(t)
        growth.append(machine.growth_um())
    return times, np.array(growth)


def test_steady_growth_at_top_speed_is_20_to_50_um_with_time_constant_20_to_90_min() -> None:
    top = SpeedProgram("top", ((12 * 3600.0, PARAMS.max_speed_rpm),))
    times, growth = growth_curve(top)
    steady = growth[-1]
    assert 20.0 <= steady <= 50.0, steady
    # Time constant: when the growth first reaches 63.2 % of its steady value.
    tau_min = times[np.argmax(growth >= 0.632 * steady)] / 60.0
    assert 20.0 <= tau_min <= 90.0, tau_min


def test_growth_grows_with_speed_and_recovers_in_the_cool_down() -> None:
    peaks = [
        growth_curve(PROGRAMS[name])[1].max() for name in ("const2000", "const4000", "const6000")
    ]
    assert peaks[0] < peaks[1] < peaks[2]
    _, growth = growth_curve(PROGRAMS["const6000"])
    assert growth[-1] < 0.5 * growth.max()


def effect_difference(program: str, effect: str) -> tuple[dict, dict, np.ndarray]:
    """Same seed with and without the effect: the noise draws are identical."""
    plain, with_effect = table(program), table(program, effect)
    return plain, with_effect, with_effect["error_um"] - plain["error_um"]


def test_speed_direct_error_jumps_at_a_speed_step_before_temperatures_move() -> None:
    plain, data, _ = effect_difference("iso230-spectrum", "speed_direct")
    changes = np.flatnonzero(np.diff(data["speed_rpm"]) != 0) + 1
    start, step = int(changes[0]), int(changes[1])  # rest → 2000, then 2000 → 6000 r/min
    assert data["time_s"][start] == REST_BEFORE_S
    assert np.all(data["speed_rpm"][:start] == 0)
    assert (data["speed_rpm"][step - 1], data["speed_rpm"][step]) == (2000.0, 6000.0)
    jump = data["error_um"][step] - data["error_um"][step - 1]
    plain_jump = plain["error_um"][step] - plain["error_um"][step - 1]
    temps = np.column_stack([data[f"T{i}"] for i in range(1, 10)])
    # -0.4·(6−2) − 0.06·(36−4) = −3.52 µm within one 60 s sample.
    assert jump == pytest.approx(plain_jump - 3.52, abs=0.1)
    assert abs(plain_jump) < 1.5
    assert np.max(np.abs(temps[step] - temps[step - 1])) <= 0.5


def test_thermal_lag_error_lags_the_sensors_in_the_cool_down() -> None:
    plain, data, _ = effect_difference("const6000", "thermal_lag")
    stop = int(np.flatnonzero(np.diff(data["speed_rpm"]) < 0)[0]) + 1

    def half_life_min(error: np.ndarray) -> float:
        """Minutes from the stop until the error is down to half, read through the noise.

        A 9-sample moving mean (the probe's 0.25 µm would otherwise move a single
        crossing by minutes) and a crossing interpolated between samples.
        """
        smooth = np.convolve(error[stop - 4 :], np.ones(9) / 9, mode="valid")
        half = 0.5 * smooth[0]
        k = int(np.argmax(smooth <= half))
        return k - 1 + float((smooth[k - 1] - half) / (smooth[k - 1] - smooth[k]))

    # 80 % of the shaft growth through a 30 min lag: the cool-down half-life grows by > 20 %
    assert half_life_min(data["error_um"]) >= 1.2 * half_life_min(plain["error_um"])
    temps = np.column_stack([data[f"T{i}"] for i in range(1, 10)])
    np.testing.assert_array_equal(temps, np.column_stack([plain[f"T{i}"] for i in range(1, 10)]))


def test_ambient_cycle_shows_in_the_ambient_column_and_moves_the_error() -> None:
    plain, data, difference = effect_difference("const4000", "ambient")
    assert np.ptp(plain["ambient_C"]) <= 0.4
    # A 6 h run covers three quarters of the 8 h cycle: up by the amplitude and back down.
    assert np.ptp(data["ambient_C"]) >= 0.8 * PARAMS.effects.ambient.amplitude_C
    # Only the column (no sensor on it) feels the hall: the machine sensors barely
    # move (a little heat conducts into the headstock), and the column's growth
    # (negative: it lifts the headstock) follows the hall with the column's lag.
    for i in range(1, 10):
        assert np.max(np.abs(data[f"T{i}"] - plain[f"T{i}"])) <= 0.35
    assert np.max(np.abs(difference)) >= 2.0
    hall = data["ambient_C"] - PARAMS.ambient_C
    lags_min = range(0, 181, 10)  # samples are 1 min apart
    corr = [np.corrcoef(difference[lag:], hall[: hall.size - lag])[0, 1] for lag in lags_min]
    best = int(np.argmin(corr))
    assert corr[best] < -0.9
    assert 30 <= lags_min[best] <= 150  # the column's thermal lag, not an instant effect


def test_drift_grows_linearly_at_its_rate() -> None:
    _, data, difference = effect_difference("const4000", "drift")
    slope_um_per_h = np.polyfit(data["time_s"] / 3600.0, difference, 1)[0]
    assert slope_um_per_h == pytest.approx(PARAMS.effects.drift.um_per_h, rel=0.01)


def dominant_period_s(signal: np.ndarray, sample_s: float = 60.0, window: int = 20) -> float:
    """Period of the strongest oscillation left after removing a moving average."""
    trend = np.convolve(signal, np.ones(window) / window, mode="same")
    detrended = (signal - trend)[window:-window]
    spectrum = np.abs(np.fft.rfft(detrended - detrended.mean()))
    freqs = np.fft.rfftfreq(detrended.size, sample_s)
    return float(1.0 / freqs[1 + np.argmax(spectrum[1:])])


def test_cooler_saw_tooth_period_in_a_bearing_sensor_and_the_error() -> None:
    period = PARAMS.effects.cooler.period_s
    plain, data, _ = effect_difference("const4000", "cooler")
    running = slice(0, 240)  # the four hours at speed
    assert dominant_period_s(data["T1"][running]) == pytest.approx(period, rel=0.1)
    assert dominant_period_s(data["error_um"][running]) == pytest.approx(period, rel=0.1)
    assert dominant_period_s(plain["T1"][running]) != pytest.approx(period, rel=0.1)


def test_closed_loop_compensation_is_applied_to_the_measured_error() -> None:
    machine = SimulatedMachine(PARAMS, PROGRAMS["const8000"], seed=3)
    machine.advance_to(3 * 3600.0)
    growth = machine.growth_um()
    assert growth > 20.0
    machine.write_macro(PARAMS.compensation.macro, growth / 1000.0)  # mm
    assert machine.true_error_um() == pytest.approx(0.0, abs=1e-9)
    assert abs(machine.measured_error_um()) < 5 * PARAMS.probe.noise_um
    assert machine.compensation_log == [(machine.time_s, growth / 1000.0)]


def test_probe_variable_publishes_the_measured_error_periodically() -> None:
    machine = SimulatedMachine(PARAMS, PROGRAMS["const4000"], seed=3)
    machine.advance_to(PARAMS.probe.period_s - PARAMS.sub_step_s)
    assert machine.probe_error_um is None
    machine.advance_to(PARAMS.probe.period_s)
    first = machine.probe_error_um
    assert first is not None and machine.macros[PARAMS.probe.macro] == first
    assert first == pytest.approx(machine.true_error_um(), abs=5 * PARAMS.probe.noise_um)


def test_sensor_faults_as_a_transmitter_reports_them() -> None:
    machine = SimulatedMachine(PARAMS, PROGRAMS["const6000"], seed=3)
    machine.add_fault(SensorFault("T1", "open_circuit", start_s=600, end_s=1200))
    machine.add_fault(SensorFault("T2", "stuck", start_s=600))
    machine.add_fault(SensorFault("T3", "spike", start_s=600, end_s=660))
    machine.add_fault(SensorFault("T4", "drift", start_s=600, magnitude_C=6.0))
    machine.advance_to(600)
    at_start = machine.readings()
    assert at_start["T1"].status is ChannelStatus.OPEN_CIRCUIT and np.isnan(at_start["T1"].value_C)
    machine.advance_to(4200)
    later = machine.readings()
    assert later["T1"].status is ChannelStatus.OK  # the fault cleared at 1200 s
    assert later["T2"].value_C == at_start["T2"].value_C  # stuck
    assert later["T3"].value_C < at_start["T3"].value_C - 30  # the spike is over
    assert later["T5"].value_C > at_start["T5"].value_C + 1  # a healthy sensor warmed up
    # drift: 6 °C/h for one hour on top of the real warming of T4
    plain = SimulatedMachine(PARAMS, PROGRAMS["const6000"], seed=3)
    plain.advance_to(4200)
    assert later["T4"].value_C - plain.readings()["T4"].value_C == pytest.approx(6.0, abs=0.3)
    with pytest.raises(ValueError, match="no sensor 'T42'"):
        machine.add_fault(SensorFault("T42", "stuck", start_s=0))


def test_programmes() -> None:
    k1, k2, k3 = (
        PROGRAMS[n] for n in ("iso230-spectrum", "spectrum-swapped", "spectrum-const4000")
    )
    assert k1.duration_s == k2.duration_s == k3.duration_s
    # K1 = part 1 (100 min), stop, part 2 (90 min), stop, part 3 (90 min), cool-down;
    # K2 swaps parts 1 and 3: K2's first 90 min are K1's part 3 (from minute 220),
    # and K2's part 1 starts at minute 90 + 15 + 90 + 15 = 210.
    minute = 60.0
    for t in np.arange(0, 90 * minute, minute):
        assert k2.speed_at(t) == k1.speed_at(t + 220 * minute)
    for t in np.arange(0, 100 * minute, minute):
        assert k1.speed_at(t) == k2.speed_at(t + 210 * minute)
    assert {k3.speed_at(t) for t in np.arange(115 * 60, 205 * 60, 60)} == {4000.0}
    assert (
        PROGRAMS["const6000"].speed_at(3600) == 6000.0
        and PROGRAMS["const6000"].speed_at(5 * 3600) == 0.0
    )
    assert production_program(5) == production_program(5) != production_program(6)
    assert program_by_name("production-5") == production_program(5)
    with pytest.raises(ValueError, match="unknown programme 'const9000'"):
        program_by_name("const9000")


def test_bad_effect_and_params_are_refused(tmp_path: Path) -> None:
    result = gateway_in_process("simulate", "--record", tmp_path / "x.csv", "--effect", "gremlins")
    assert result.returncode == 2 and "unknown hidden effect(s) ['gremlins']" in result.stderr
    bad = tmp_path / "params.yaml"
    bad.write_text("heat_capacity_J_per_K: {bearing: -5}\n")
    result = gateway_in_process("simulate", "--record", tmp_path / "x.csv", "--params", bad)
    assert result.returncode == 2 and "heat capacities must be > 0" in result.stderr
