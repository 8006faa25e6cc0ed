"""`python -m gateway run` and `simulate` as two processes, one config file, as on a bench."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

from models.data.dataset import load_runs
from tests import gateway_rig as rig
from tests import served_bench as bench
from tests.cli import gateway as gateway_cli
from tests.cli import gateway_in_process
from tests.ports import free_tcp_port
from tests.served_bench import gateway_process, read_macro_mm, wait_until


def bench_config(tmp_path: Path, bus: int, cnc: int) -> Path:
    """One machine on the simulator's TCP bus and Modbus CNC; models fitted into tmp_path."""
    config = bench.bench_config(rig.fit_store(tmp_path), bus, cnc, speedup=300)
    config["state_dir"] = str(tmp_path / "state")
    config["logging"] = {"local_store": str(tmp_path / "data" / "points.sqlite")}
    # A probe every 2 machine minutes: 0.4 s of wall time at ×300.
    config["simulator"]["probe"] = {"period_s": 120.0}
    config["machines"][0]["compensation"]["probe_macro"] = 600
    return bench.write_config(config, tmp_path / "config.yaml")


def test_run_compensates_the_served_machine_and_stops_on_sigterm(tmp_path: Path) -> None:
    bus, cnc = free_tcp_port(), free_tcp_port()
    path = bench_config(tmp_path, bus, cnc)
    with bench.simulator_serving(path, cnc):
        gateway = gateway_process("run", "--config", path)
        try:
            compensates_logs_and_stops(tmp_path, path, cnc, gateway)
        finally:
            bench.kill_if_running(gateway)


def compensates_logs_and_stops(
    tmp_path: Path, path: Path, cnc: int, gateway: subprocess.Popen[str]
) -> None:
    """The served machine compensated and probed; SIGTERM; what was logged fits again."""
    # ×300: 8 s of wall time are 40 min at 8000 r/min; the spindle grows > 10 µm.
    # Every wait below ends on what the machine shows, not on a fixed sleep.
    values: list[float] = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (values and values[-1] > 0.005):
        time.sleep(0.2)
        values.append(read_macro_mm(cnc))
    assert values and values[-1] > 0.005, values  # > 5 µm of compensation written
    # Then at least 12 more probe measurements (#600 changes at each one).
    probes = {read_macro_mm(cnc, 600)}
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(probes) < 13:
        time.sleep(0.1)
        probes.add(read_macro_mm(cnc, 600))
        values.append(read_macro_mm(cnc))
    assert len(probes) >= 13, probes
    assert all(abs(v) <= 0.050 for v in values)  # within the ±50 µm clamp
    gateway.send_signal(signal.SIGTERM)
    out, err = gateway.communicate(timeout=30)
    assert gateway.returncode == 0, err
    assert "running 1 machine(s): bench-1" in out and "stopped" in out
    assert "CNC macro #500 holds" in err  # the loop read the macro before writing
    assert (tmp_path / "state" / "bench-1-reference.json").exists()
    assert (tmp_path / "state" / "bench-1-heartbeat.json").exists()
    # Everything measured and decided was logged: export it and fit on it again.
    exported = tmp_path / "exported.csv"
    result = gateway_cli("export", exported, "--config", path)
    assert result.returncode == 0, result.stderr
    assert "from local store" in result.stdout
    data = load_runs(exported)
    assert data.n_samples >= 10  # one row per probe measurement (every 120 s)
    assert data.sensors == tuple(f"T{i}" for i in range(1, 10))
    fitted = gateway_in_process("fit", exported, "--method", "mlr", "--store", tmp_path / "refit")
    assert fitted.returncode == 0, fitted.stderr
    assert "pooled" in fitted.stdout


def test_a_second_run_on_the_same_state_dir_is_refused_and_a_killed_one_leaves_no_lock(
    tmp_path: Path,
) -> None:
    """Two gateways on one configuration would both write #500; the second is refused
    before it connects to anything, and the first compensates on undisturbed."""
    bus, cnc = free_tcp_port(), free_tcp_port()
    path = bench_config(tmp_path, bus, cnc)
    with bench.simulator_serving(path, cnc, signal.SIGTERM):
        first = third = None
        heartbeat = tmp_path / "state" / "bench-1-heartbeat.json"
        try:
            first = gateway_process("run", "--config", path)
            assert wait_until(heartbeat.exists)
            second = gateway_cli("run", "--config", path, timeout_s=60)
            assert second.returncode == 2, second.stdout + second.stderr
            assert second.stderr.splitlines() == [
                f"error: {path}: state_dir {tmp_path / 'state'}: another gateway (pid {first.pid}) "
                "is running on it; two would write the same CNC macros and state files: stop that "
                "one, or give this one a state_dir of its own"
            ]
            assert "running" not in second.stdout
            # The first one goes on: its heartbeat is renewed after the refusal.
            refused_at = heartbeat.stat().st_mtime
            assert wait_until(lambda: heartbeat.stat().st_mtime > refused_at, 20)
            assert first.poll() is None
            # kill -9 leaves the lock file behind but not the lock: a restart runs.
            first.kill()
            first.communicate(timeout=30)
            assert (tmp_path / "state" / "gateway.lock").exists()
            killed_at = heartbeat.stat().st_mtime
            third = gateway_process("run", "--config", path)
            assert wait_until(lambda: heartbeat.stat().st_mtime > killed_at)
            assert third.poll() is None
            third.send_signal(signal.SIGTERM)
            out, err = third.communicate(timeout=30)
            assert third.returncode == 0, err
            assert "running 1 machine(s): bench-1" in out and "stopped" in out
        finally:
            bench.kill_if_running(first, third)


def test_run_with_a_damaged_cold_reference_stops_before_connecting_naming_the_file(
    tmp_path: Path,
) -> None:
    """A power cut left the reference empty: no new (possibly warm) first reading is taken."""
    path = bench_config(tmp_path, free_tcp_port(), free_tcp_port())  # nothing listens there
    saved = tmp_path / "state" / "bench-1-reference.json"
    saved.parent.mkdir(parents=True)
    saved.write_bytes(b"")
    result = gateway_cli("run", "--config", path, timeout_s=60)
    assert result.returncode == 2, result.stdout + result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert errors == [
        f"error: {saved}: the machine's saved cold reference is unreadable (Expecting value: "
        "line 1 column 1 (char 0)); restore the file, or delete it to take a new reference "
        "with the machine cold"
    ]
    assert "running" not in result.stdout and saved.read_bytes() == b""
    assert not (tmp_path / "state" / "bench-1-heartbeat.json").exists()


def test_run_with_a_damaged_local_store_keeps_it_aside_and_runs_on(tmp_path: Path) -> None:
    path = bench_config(tmp_path, free_tcp_port(), free_tcp_port())  # nothing listens there
    store = tmp_path / "data" / "points.sqlite"
    store.parent.mkdir(parents=True)
    store.write_bytes(b"not a database\n" * 200)
    heartbeat = tmp_path / "state" / "bench-1-heartbeat.json"
    gateway = gateway_process("run", "--config", path)
    try:
        assert wait_until(heartbeat.exists) and gateway.poll() is None
    finally:
        gateway.send_signal(signal.SIGTERM)
        _, err = gateway.communicate(timeout=30)
    assert gateway.returncode == 0, err
    (aside,) = store.parent.glob("points.sqlite.unreadable-*")
    assert aside.read_bytes() == b"not a database\n" * 200
    told = f"{store}: not a readable SQLite database (file is not a database); kept as {aside}"
    assert told in err
    assert store.read_bytes().startswith(b"SQLite format 3\x00")
