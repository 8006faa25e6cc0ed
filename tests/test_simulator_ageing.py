"""The simulator's probe cycle (period, noise) from the config and the CLI, and machine ageing.

The probe cycle is read the way the gateway reads it: the probe macro over
Modbus TCP, from a served plant on a manual clock (machine time) and from a
``python -m gateway simulate`` process. Ageing is checked on recorded runs
against the same run without it: the coolant offset adds rate · days µm, the
preload drift scales the bearing's growth by 1 + gain · days; with ageing off a
recording keeps the bytes it had before ageing existed
(``tests/cases/simulator/record-const2000-seed5.csv``).
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from pymodbus.client import AsyncModbusTcpClient

from drivers.clock import ManualClock
from simulator.machine import SimulatedMachine
from simulator.params import load_params
from simulator.programs import SpeedProgram
from simulator.record import record
from simulator.serve import SimulatedPlant, SimulatorConfig
from simulator.servers.modbus_cnc import macro_register
from simulator.thermal import ThermalNetwork
from tests.cli import ROOT, gateway, gateway_in_process
from tests.ports import free_tcp_port

PARAMS = load_params()
GOLDEN = ROOT / "tests" / "cases" / "simulator" / "record-const2000-seed5.csv"
DAY_S = 86400.0


# --- probe cycle ----------------------------------------------------------------------
async def read_macro(client: AsyncModbusTcpClient, number: int) -> float:
    rr = await client.read_holding_registers(macro_register(number), count=2, device_id=1)
    return client.convert_from_registers(rr.registers, client.DATATYPE.FLOAT32, word_order="big")


async def probe_values(config: dict, step_s: float, steps: int) -> list[tuple[float, float]]:
    """(machine time, probe macro) read over Modbus TCP after each clock step."""
    clock = ManualClock()
    plant = SimulatedPlant(SimulatorConfig.model_validate(config), clock=clock)
    assert plant.cnc_modbus is not None
    seen = []
    async with plant:
        host, port = plant.cnc_modbus.address
        client = AsyncModbusTcpClient(host, port=port, timeout=2)
        await client.connect()
        try:
            for _ in range(steps):
                clock.advance(step_s)
                await plant.update()
                seen.append((clock.now(), await read_macro(client, PARAMS.probe.macro)))
        finally:
            client.close()
    return seen


def served_config(**probe: float) -> dict:
    return {
        "program": "const4000",
        "seed": 4,
        "probe": probe,
        "cnc": {"modbus": {"port": free_tcp_port()}},
    }


def test_probe_period_from_the_config_in_machine_time() -> None:
    seen = asyncio.run(probe_values(served_config(period_s=120.0), step_s=20.0, steps=60))
    changes = [t for (t, v), (_, before) in zip(seen[1:], seen, strict=False) if v != before]
    # The macro starts at 0 and gets a new value at every 120 s of machine time, not between.
    assert changes == [float(t) for t in range(120, 1201, 120)]
    assert seen[4][1] == 0.0 and seen[5][1] != 0.0  # the first probe lands at 120 s


def test_probe_noise_from_the_config_matches_its_scatter() -> None:
    steps = 300
    quiet = asyncio.run(probe_values(served_config(period_s=60.0, noise_um=0.0), 60.0, steps))
    noisy = asyncio.run(probe_values(served_config(period_s=60.0, noise_um=1.5), 60.0, steps))
    scatter = np.array([v for _, v in noisy]) - np.array([v for _, v in quiet])
    # Same seed, same machine time: the difference is the probe noise alone.
    assert abs(scatter.mean()) < 0.3
    assert scatter.std() == pytest.approx(1.5, rel=0.15)


def test_bad_probe_settings_are_refused_with_their_key() -> None:
    with pytest.raises(ValueError, match=r"probe\.period_s"):
        SimulatorConfig.model_validate(served_config(period_s=0.0))
    with pytest.raises(ValueError, match=r"probe\.noise_um"):
        SimulatorConfig.model_validate(served_config(noise_um=-1.0))


def test_cli_probe_options_win_over_the_config_when_serving(tmp_path: Path) -> None:
    """``simulate --probe-period-s``: new probe values arrive at that period (×3600 speed-up)."""
    port = free_tcp_port()
    config = {
        "simulator": {
            "program": "const4000",
            "speedup": 3600,
            "publish_period_s": 0.05,
            "probe": {"period_s": 60.0},
            "cnc": {"modbus": {"port": port}},
        }
    }
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config), encoding="utf-8")
    command = [sys.executable, "-m", "gateway", "simulate", "--config", path]
    command += ["--probe-period-s", "3600", "--probe-noise-um", "0.5"]
    process = subprocess.Popen(
        list(map(str, command)), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    try:
        arrivals = asyncio.run(watch_probe_macro(port, changes=3, timeout_s=40.0))
    finally:
        process.terminate()
        process.wait(timeout=10)
    gaps_s = np.diff(arrivals)
    # 3600 machine s at ×3600 is one wall second between probes (60 s would be 1/60 s).
    # (A busy host may delay one publish; the next gap is then shorter by as much.)
    assert np.all(gaps_s > 0.4) and 0.75 < gaps_s.mean() < 1.3, gaps_s


async def watch_probe_macro(port: int, changes: int, timeout_s: float) -> list[float]:
    """Wall-clock times at which the probe macro took a new value."""
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=2)
    deadline = time.monotonic() + timeout_s
    while not await client.connect():
        assert time.monotonic() < deadline, "the simulator did not come up"
        await asyncio.sleep(0.2)
    arrivals: list[float] = []
    try:
        last = await read_macro(client, PARAMS.probe.macro)
        while len(arrivals) < changes + 1 and time.monotonic() < deadline:
            value = await read_macro(client, PARAMS.probe.macro)
            if value != last:
                arrivals.append(time.monotonic())
                last = value
            await asyncio.sleep(0.01)
    finally:
        client.close()
    assert len(arrivals) == changes + 1, arrivals
    return arrivals[1:]  # the first change may have been under way when we started


def test_cli_probe_noise_when_recording(tmp_path: Path) -> None:
    quiet, noisy = tmp_path / "quiet.csv", tmp_path / "noisy.csv"
    for path, noise in ((quiet, "0"), (noisy, "2.0")):
        result = gateway_in_process(
            "simulate", "--record", path, "--program", "const4000", "--seed", 3,
            "--probe-noise-um", noise, "--probe-period-s", 120,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
    error = {p: np.loadtxt(p, delimiter=",", skiprows=1, usecols=-1) for p in (quiet, noisy)}
    scatter = error[noisy] - error[quiet]
    assert len(scatter) > 300
    assert scatter.std() == pytest.approx(2.0, rel=0.12)


# --- ageing ---------------------------------------------------------------------------
def soak_errors(ageing: dict | None, days: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, error_um) of a constant-4000 r/min run over ``days``, sampled hourly."""
    params = PARAMS if ageing is None else load_params({"ageing": ageing})
    soak = SpeedProgram("soak", ((days * DAY_S, 4000.0),))
    recording = record(params, [soak], seed=9, sample_s=3600.0)
    error = recording.header.index("error_um")
    return np.array([r[1] for r in recording.rows]), np.array([r[error] for r in recording.rows])


def test_coolant_offset_grows_by_its_rate_per_machine_day() -> None:
    time_s, plain = soak_errors(None)
    _, aged = soak_errors({"coolant_offset_um_per_day": 1.5})
    assert time_s[-1] >= 4 * DAY_S
    # Same seed: the difference is the offset alone, 1.5 µm a day (0.01 µm rounding each).
    np.testing.assert_allclose(aged - plain, 1.5 * time_s / DAY_S, atol=0.011)
    assert (aged - plain)[-1] == pytest.approx(6.0, abs=0.2)


def test_preload_drift_scales_the_bearing_growth_share() -> None:
    time_s, plain = soak_errors(None)
    _, aged = soak_errors({"preload_gain_per_day": 0.05})
    # After four days at 4000 r/min the network is settled: the bearing's growth
    # is 1.0 µm/K × its steady rise, scaled by 0.05 × days more.
    bearing_rise_K = ThermalNetwork(PARAMS, PARAMS.sub_step_s).steady_state(4000.0, 20.0)[0] - 20.0
    bearing_um = PARAMS.growth_um_per_K["bearing"] * bearing_rise_K
    settled = time_s > 1 * DAY_S
    expected = 0.05 * time_s[settled] / DAY_S * bearing_um
    np.testing.assert_allclose((aged - plain)[settled], expected, atol=0.03)
    assert expected[-1] > 1.0  # a visible drift: a fitted model goes stale


def test_ageing_follows_machine_time_from_the_machines_start() -> None:
    """Age counts from the machine's own start (a served machine's clock is not at 0)."""
    params = load_params({"ageing": {"coolant_offset_um_per_day": 2.0, "start_days": 10.0}})
    soak = SpeedProgram("soak", ((3 * DAY_S, 0.0),))
    machine = SimulatedMachine(params, soak, start_s=1.7e9)
    assert machine.age_days == 10.0 and machine.growth_um() == pytest.approx(20.0)
    machine.advance_to(1.7e9 + DAY_S)
    assert machine.age_days == pytest.approx(11.0)
    assert machine.growth_um() == pytest.approx(22.0, abs=1e-6)


def test_without_ageing_a_recording_keeps_its_bytes(tmp_path: Path) -> None:
    plain, zero = tmp_path / "plain.csv", tmp_path / "zero.csv"
    params = tmp_path / "ageing-off.yaml"
    params.write_text(
        "ageing: {preload_gain_per_day: 0.0, coolant_offset_um_per_day: 0.0, start_days: 30}\n",
        encoding="utf-8",
    )
    common = ("--program", "const2000", "--seed", 5, "--sample-s", 300)
    assert gateway_in_process("simulate", "--record", plain, *common).returncode == 0
    result = gateway_in_process("simulate", "--record", zero, *common, "--params", params)
    assert result.returncode == 0, result.stderr
    assert plain.read_bytes() == GOLDEN.read_bytes()
    assert zero.read_bytes() == GOLDEN.read_bytes()


def test_ageing_from_a_params_file_on_the_cli(tmp_path: Path) -> None:
    """A machine 30 days old with a 0.5 µm/day coolant offset: 15 µm more, then 0.5 µm/day."""
    aged = tmp_path / "aged.csv"
    params = tmp_path / "aged.yaml"
    params.write_text(
        "ageing: {coolant_offset_um_per_day: 0.5, start_days: 30}\n", encoding="utf-8"
    )
    result = gateway_in_process(
        "simulate", "--record", aged, "--program", "const2000", "--seed", 5,
        "--sample-s", 300, "--params", params,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    error = GOLDEN.read_text(encoding="utf-8").splitlines()[0].split(",").index("error_um")
    table = np.loadtxt(aged, delimiter=",", skiprows=1, usecols=(1, error))
    golden = np.loadtxt(GOLDEN, delimiter=",", skiprows=1, usecols=(1, error))
    np.testing.assert_array_equal(table[:, 0], golden[:, 0])
    expected = 0.5 * (30.0 + table[:, 0] / DAY_S)
    np.testing.assert_allclose(table[:, 1] - golden[:, 1], expected, atol=0.011)


def test_bad_ageing_key_in_the_config_is_one_located_error(tmp_path: Path) -> None:
    lines = (ROOT / "config.yaml").read_text(encoding="utf-8").splitlines()
    at = lines.index("simulator:") + 1
    lines.insert(at, "  ageing: {preload_gain_per_dya: 0.01}")
    bad = tmp_path / "config.yaml"
    bad.write_text("\n".join(lines) + "\n", encoding="utf-8")
    result = gateway("check-config", "--config", bad, timeout_s=120)
    assert result.returncode == 2
    assert "Traceback" not in result.stdout + result.stderr
    assert result.stderr.splitlines() == [
        f"error: {bad}:{at + 1}: simulator.ageing.preload_gain_per_dya: "
        "unknown key (not part of the configuration)"
    ]
