"""SIGTERM/SIGINT stop `python -m gateway run` within 1 s, whatever the cycle, with state saved.

Two processes, as on a bench: `simulate` serves the machine (Modbus TCP
transmitters and CNC), `run` compensates it with a five-minute cycle, logs to
InfluxDB through the disk buffer (the database is down: nothing listens on its
port, so every point stays buffered) and serves SCADA; its model store holds an
augmented model, whose lag state the loop keeps in the state folder.

First the gateway runs with a 1 s cycle until it has taken the cold reference
(a sensor is trusted after 3 good cycles) and is stopped; then it starts again
with a five-minute cycle, runs its first cycle from the saved reference, and the
signal arrives while the loop sleeps towards the second.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from gateway.outputs.disk_buffer import PointBuffer
from models.analysis import augmented
from models.online.streaming import TIME_KEY
from simulator.params import load_params
from simulator.programs import program_by_name
from simulator.record import DEFAULT_PROGRAMS, record, write_recording
from tests import gateway_rig as rig
from tests import served_bench as bench
from tests.cli import gateway_in_process
from tests.ports import free_tcp_port

CYCLE_S = 300.0
STOP_LIMIT_S = 1.0


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo's models plus an augmented one (lag terms), whose state the loop saves."""
    folder = tmp_path_factory.mktemp("shutdown")
    models = rig.fit_store(folder)
    data = folder / "hidden.csv"
    programs = [program_by_name(name) for name in DEFAULT_PROGRAMS]
    write_recording(data, record(load_params(), programs, ["thermal_lag", "speed_direct"], seed=2))
    done = gateway_in_process("analyze", data, "--model", "mlr", "--store", models)
    assert done.returncode == 0, done.stderr
    assert list((models / augmented.FOLDER).glob("*.json"))
    return models


def effect_times_s(path: Path) -> dict[str, float]:
    """Machine time of each augmented model's saved lag state."""
    saved = json.loads(path.read_text())["models"]
    return {model_id: entry["state"][TIME_KEY] for model_id, entry in saved.items()}


def write_config(tmp_path: Path, store: Path, cycle_s: float) -> tuple[Path, int]:
    bus, cnc = free_tcp_port(), free_tcp_port()
    password_file = tmp_path / "viewer.secret"
    password_file.write_text("view-secret-3\n")
    config = {
        "state_dir": str(tmp_path / "state"),
        "logging": {
            "influxdb": {"url": f"http://127.0.0.1:{free_tcp_port()}", "bucket": "gateway/autogen"},
            "buffer_path": str(tmp_path / "data" / "buffer.sqlite"),
        },
        "scada": {
            "port": free_tcp_port(),
            "pki_dir": str(tmp_path / "pki"),
            "users": [{"username": "victor", "password_file": str(password_file)}],
        },
    }
    config |= bench.bench_config(store, bus, cnc, speedup=1, cycle_s=cycle_s)
    (machine,) = config["machines"]
    machine["sensors"] = {name: {"stale_s": 2 * CYCLE_S} for name in rig.SENSORS}
    del machine["plausibility"], machine["compensation"]  # this bench keeps the defaults
    return bench.write_config(config, tmp_path / "config.yaml"), cnc


def run_until_stopped(
    config: Path, ready: Path, signum: signal.Signals
) -> tuple[float, subprocess.CompletedProcess[str]]:
    """Serve the simulated machine, run the gateway until ``ready`` exists and one
    second more, send ``signum``; (seconds from the signal to the exit, the run)."""
    cnc = yaml.safe_load(config.read_text())["simulator"]["cnc"]["modbus"]["port"]
    with bench.simulator_serving(config, cnc):
        gateway = bench.gateway_process("run", "--config", config)
        try:
            bench.wait_for_file(ready, gateway, timeout_s=60)
            time.sleep(1.0)  # the cycle is done; the loop sleeps towards the next one
            sent = time.monotonic()
            gateway.send_signal(signum)
            gateway.wait(timeout=30)
            stopped_s = time.monotonic() - sent
            out, err = gateway.communicate()
        finally:
            bench.kill_if_running(gateway)
    return stopped_s, subprocess.CompletedProcess(gateway.args, gateway.returncode, out, err)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_stops_a_sleeping_loop_within_a_second_with_state_saved(
    tmp_path: Path, store: Path, signum: signal.Signals
) -> None:
    state = tmp_path / "state"
    reference_file = state / "bench-1-reference.json"
    first, _ = write_config(tmp_path, store, cycle_s=1.0)
    first_stop_s, done = run_until_stopped(first, reference_file, signum)
    assert done.returncode == 0, done.stderr
    assert first_stop_s < STOP_LIMIT_S, f"stopped {first_stop_s:.2f} s after {signum.name}"
    reference = json.loads(reference_file.read_text())["reference_C"]
    assert sorted(reference) == sorted(rig.SENSORS)
    # The lag states were saved at the stop: as of the last cycle, not the last periodic save
    # (every 60 s of machine time; this run was shorter).
    # The heartbeat carries the last cycle's wall stamp, the lag states its machine time
    # (monotonic from the wall time at the start): the same within ms on a short run, and
    # a whole cycle (1 s) apart from any other cycle's.
    last_cycle_s = json.loads((state / "bench-1-heartbeat.json").read_text())["time_s"]
    effect_file = state / "bench-1-effect-state.json"
    first_effects = effect_times_s(effect_file)
    assert len(set(first_effects.values())) == 1
    assert next(iter(first_effects.values())) == pytest.approx(last_cycle_s, abs=0.1)
    with PointBuffer(tmp_path / "data" / "buffer.sqlite") as buffer:
        first_points = len(buffer)
    assert first_points > 0

    second, _ = write_config(tmp_path, store, cycle_s=CYCLE_S)
    (state / "bench-1-heartbeat.json").unlink()
    stopped_s, done = run_until_stopped(second, state / "bench-1-heartbeat.json", signum)
    assert done.returncode == 0, done.stderr
    print(f"{signum.name}: stopped {first_stop_s:.2f} s (1 s cycle), {stopped_s:.2f} s (300 s)")
    assert stopped_s < STOP_LIMIT_S, f"stopped {stopped_s:.2f} s after {signum.name}"
    assert "stopped" in done.stdout
    assert "Traceback" not in done.stderr
    # The reference was kept across the restart; one cycle ran, and was logged.
    assert json.loads(reference_file.read_text())["reference_C"] == reference
    beat = json.loads((state / "bench-1-heartbeat.json").read_text())
    assert beat["cycles"] == 1
    # Kept, not reset: no sensor is trusted in the first cycle after a start (3 good
    # cycles are needed), so the lags wait, and the stop saved them as they were.
    assert effect_times_s(effect_file) == first_effects
    # Every point of both runs is in the disk buffer, for the forwarder of the next start.
    with PointBuffer(tmp_path / "data" / "buffer.sqlite") as buffer:
        points = [point for _, point in buffer.peek(100_000)]
    assert len(points) > first_points
    assert all(p.tags.get("machine") == "bench-1" for p in points)
    assert beat["health"]["forwarder_backlog"] == len(points)
