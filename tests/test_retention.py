"""Bounded disk: retention of the local store and the disk buffer, and a full disk survived.

The size and age bounds are checked on real SQLite files. The full disk is a real
one: a small tmpfs mounted for the test (the suite runs as root, as CI does), filled
with a filler file until the kernel answers ENOSPC, then freed again.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.config import GatewayConfig
from gateway.live.record import CycleRecord
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.heartbeat import heartbeat_path
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import Point
from gateway.outputs.sinks import Outputs
from gateway.process.file_writer import HEARTBEATS
from tests import gateway_rig as rig
from tests import served_bench as bench
from tests.ports import free_tcp_port
from tests.records import written_record
from tests.served_bench import read_macro_mm, rises

NS = 1_000_000_000
T0_NS = 1_780_000_000 * NS  # an arbitrary Unix time, s → ns


def cycle_points(machine: str, second: int, sensors: int = 9) -> list[Point]:
    """The ten points of one logged cycle (as gateway.outputs.points makes them)."""
    ns = T0_NS + second * NS
    tags = {"machine": machine, "regime": "variable", "model_id": "mlr-error_um-variable"}
    fields = {"speed_rpm": 4000.0, "predicted_um": 3.25, "applied_um": 3.0, "write_status": "ok"}
    points = [Point("spindle_cycle", tags, fields, ns)]
    for i in range(1, sensors + 1):
        sensor_tags = {"machine": machine, "sensor": f"T{i}", "quality": "good"}
        points.append(Point("spindle_temperature", sensor_tags, {"value_C": 20.0 + i}, ns))
    return points


# --- age ----------------------------------------------------------------------------------
def test_local_store_deletes_points_past_their_age(tmp_path: Path) -> None:
    with LocalStore(tmp_path / "points.sqlite", retention_s=3600.0) as store:
        for second in range(0, 7200, 60):  # two hours, one cycle a minute
            store.write(cycle_points("vmc-1", second))
        assert len(store) == 120 * 10
        now_ns = T0_NS + 7200 * NS
        deleted = store.enforce_retention(now_ns)
        assert deleted == 60 * 10 and store.expired == deleted
        kept = store.query("spindle_cycle", "vmc-1")
        assert kept[0].time_ns == now_ns - 3600 * NS  # the first point inside the hour
        assert store.enforce_retention(now_ns) == 0


def test_buffer_drops_points_past_their_age_and_counts_them(tmp_path: Path) -> None:
    with PointBuffer(tmp_path / "buffer.sqlite", retention_s=600.0) as buffer:
        for second in range(0, 1800, 10):
            buffer.append(cycle_points("vmc-1", second))
        now_ns = T0_NS + 1800 * NS
        assert buffer.enforce_retention(now_ns) == 120 * 10
        assert buffer.dropped == 1200 and len(buffer) == 600
        (_, oldest), *_ = buffer.peek(1)
        assert oldest.time_ns == now_ns - 600 * NS
    with PointBuffer(tmp_path / "buffer.sqlite") as reopened:
        assert reopened.dropped == 1200  # the count is kept in the file


# --- size ---------------------------------------------------------------------------------
def test_local_store_stays_within_its_size_and_keeps_the_newest(tmp_path: Path) -> None:
    seconds = 6000  # 60 000 points, twice what fits
    with LocalStore(tmp_path / "whole.sqlite") as whole:
        for second in range(seconds):
            whole.write(cycle_points("vmc-1", second))
        max_bytes = whole.used_bytes() // 2
    path = tmp_path / "points.sqlite"
    with LocalStore(path, max_bytes=max_bytes) as store:
        for second in range(seconds):
            assert store.write(cycle_points("vmc-1", second))
        assert path.stat().st_size <= max_bytes
        assert store.used_bytes() <= max_bytes
        assert store.evicted > 0 and store.dropped == 0
        kept = store.query("spindle_cycle", "vmc-1")
        assert kept[-1].time_ns == T0_NS + (seconds - 1) * NS  # the newest is there
        assert kept[0].time_ns > T0_NS  # the oldest made room
        assert [p.time_ns for p in kept] == sorted(p.time_ns for p in kept)
        stored = len(store)
        assert stored + store.evicted == seconds * 10  # every point stored or evicted
        print(f"{max_bytes / stored:.0f} bytes per point at the cap", file=sys.stderr)


def test_buffer_stays_within_its_size_dropping_the_oldest(tmp_path: Path) -> None:
    max_bytes = 2_000_000
    path = tmp_path / "buffer.sqlite"
    with PointBuffer(path, max_points=10**7, max_bytes=max_bytes) as buffer:
        for second in range(4000):
            assert buffer.append(cycle_points("vmc-1", second))
        assert path.stat().st_size <= max_bytes
        assert buffer.dropped > 0
        assert len(buffer) + buffer.dropped == 40_000
        batch = buffer.peek(len(buffer))
        assert batch[-1][1].time_ns == T0_NS + 3999 * NS
        assert [row_id for row_id, _ in batch] == sorted(row_id for row_id, _ in batch)


# --- a real full disk ---------------------------------------------------------------------
@contextlib.contextmanager
def small_disk(path: Path, size: str = "2m") -> Iterator[Path]:
    """A tmpfs of ``size`` at ``path`` (needs root, as the suite and CI run)."""
    path.mkdir()
    mount = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size},mode=0777", "tmpfs", str(path)],
        capture_output=True,
        text=True,
    )
    if mount.returncode != 0:
        raise RuntimeError(f"cannot mount a tmpfs for the full-disk test: {mount.stderr}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def fill(disk: Path) -> Path:
    """Take every free byte of ``disk`` with one file (the kernel says ENOSPC at the end)."""
    filler = disk / "filler"
    with open(filler, "wb", buffering=0) as handle, contextlib.suppress(OSError):
        while True:
            handle.write(b"\0" * 4096)
    return filler


def test_full_disk_drops_and_counts_then_recovers(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    with small_disk(tmp_path / "disk") as disk:
        store = LocalStore(disk / "points.sqlite")
        buffer = PointBuffer(disk / "buffer.sqlite")
        try:
            assert store.write(cycle_points("vmc-1", 0)) and buffer.append(cycle_points("vmc-1", 0))
            filler = fill(disk)
            lost_store = lost_buffer = 0
            for second in range(1, 2000):  # until the WAL files cannot grow either
                lost_store += not store.write(cycle_points("vmc-1", second))
                lost_buffer += not buffer.append(cycle_points("vmc-1", second))
                if lost_store > 5 and lost_buffer > 5:
                    break
            assert lost_store > 5 and store.dropped == 10 * lost_store
            assert lost_buffer > 5 and buffer.dropped == 10 * lost_buffer
            assert "cannot store points" in caplog.text and "cannot keep points" in caplog.text
            # A sent batch the full disk will not let go of is not sent twice.
            held = len(buffer)
            sent = buffer.peek(5)
            assert buffer.remove_through(sent[-1][0]) == 5 and len(buffer) == held - 5
            assert all(row_id > sent[-1][0] for row_id, _ in buffer.peek(held))

            filler.unlink()  # space returns
            assert store.write(cycle_points("vmc-1", 5000))
            assert buffer.append(cycle_points("vmc-1", 5000))
            assert "local store" in caplog.text and "writable again" in caplog.text
            assert store.query("spindle_cycle", "vmc-1")[-1].time_ns == T0_NS + 5000 * NS
            remaining = buffer.peek(10**6)
            assert remaining[-1][1].time_ns == T0_NS + 5000 * NS
            assert len(buffer) == len(remaining)
        finally:
            store.close()
            buffer.close()
    with PointBuffer(tmp_path / "reopen.sqlite") as empty:  # the module still works after
        assert empty.dropped == 0


def test_gateway_compensates_on_with_a_full_disk_and_logs_again_after(tmp_path: Path) -> None:
    bus, cnc = free_tcp_port(), free_tcp_port()
    config = bench.bench_config(rig.fit_store(tmp_path), bus, cnc, speedup=120)
    with small_disk(tmp_path / "data") as data:
        config["state_dir"] = str(data / "state")
        config["logging"] = {"local_store": str(data / "points.sqlite")}
        path = bench.write_config(config, tmp_path / "config.yaml")
        with bench.simulator_serving(path, cnc):
            gateway = bench.gateway_process("run", "--config", path)
            try:
                err = compensates_through_a_full_disk(data, cnc, gateway)
            finally:
                bench.kill_if_running(gateway)
        assert "cannot store points" in err, err[-3000:]
        assert "writable again" in err and "dropped in all" in err, err[-3000:]
        with LocalStore(data / "points.sqlite") as store:
            assert len(store.query("spindle_cycle", "bench-1")) > 0


def macro_rises(cnc: int, within_s: float) -> list[float]:
    """#500 read every 0.5 s until it has risen twice (compensation at work)."""
    values = [read_macro_mm(cnc)]
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline and rises(values) < 2:
        time.sleep(0.5)
        values.append(read_macro_mm(cnc))
    return values


def compensates_through_a_full_disk(data: Path, cnc: int, gateway: subprocess.Popen[str]) -> str:
    """#500 rises before, while and after ``data`` is full; the gateway's stderr at its stop."""
    before = macro_rises(cnc, 40)
    assert rises(before) >= 2, before
    filler = fill(data)
    time.sleep(3)  # the WAL fills what was left; from here on points are dropped
    during = macro_rises(cnc, 30)
    assert rises(during) >= 2, during
    time.sleep(10)  # the store's last page of the disk fills too: points are dropped
    assert gateway.poll() is None, "the gateway must keep running on a full disk"
    filler.unlink()
    time.sleep(3)
    gateway.send_signal(signal.SIGTERM)
    _, err = gateway.communicate(timeout=30)
    assert gateway.returncode == 0, err[-3000:]
    return err


# --- the gateway's outputs: wall-clock stamps and retention actually run -------------------
def outputs_config(tmp_path: Path, **logging_keys: object) -> GatewayConfig:
    return GatewayConfig.model_validate(
        {
            "state_dir": str(tmp_path / "state"),
            "logging": {"local_store": str(tmp_path / "points.sqlite"), **logging_keys},
            "machines": [
                {
                    "id": "vmc-1",
                    "transmitters": [
                        {
                            "name": "bus",
                            "tcp": {"host": "127.0.0.1", "port": 502},
                            "devices": [{"device_id": 1, "channels": ["T1"]}],
                        }
                    ],
                    "cnc": {"modbus": {"host": "127.0.0.1", "port": 502}},
                    "models": {"store": str(tmp_path / "models")},
                }
            ],
        }
    )


def record_at(time_s: float) -> CycleRecord:
    return written_record("vmc-1", time_s, {"T1": 21.5}, 2.0, model_id="mlr-error_um-variable")


def test_points_carry_the_cycles_wall_stamp_not_its_machine_time(tmp_path: Path) -> None:
    """In the plant a record's machine time runs on the monotonic clock and its stamp is
    the wall time of the cycle's start; the points carry the stamp (and so follow an NTP
    step that machine time does not), and the heartbeat the same time."""
    outputs = Outputs(outputs_config(tmp_path))
    first, second = record_at(5000.0), record_at(5001.0)  # machine time: 1 s apart
    first.stamp_s = T0_NS / NS
    second.stamp_s = T0_NS / NS + 3_601.0  # NTP stepped the system clock by an hour
    try:
        outputs.sink(first)
        outputs.sink(second)
    finally:
        assert outputs.store is not None
        stamps = [p.time_ns for p in outputs.store.query("spindle_cycle", "vmc-1")]
        temperatures = [p.time_ns for p in outputs.store.query("spindle_temperature", "vmc-1")]
        outputs.store.close()
    assert stamps == [T0_NS, T0_NS + 3_601 * NS]
    assert temperatures == stamps
    HEARTBEATS.flush(5.0)
    beat = json.loads(heartbeat_path(tmp_path / "state", "vmc-1").read_text())
    assert beat["time_s"] == T0_NS / NS + 3_601.0 and beat["cycles"] == 2


def test_outputs_run_retention_every_interval(tmp_path: Path) -> None:
    config = outputs_config(
        tmp_path, local_store_retention_days=1 / 86_400, retention_interval_s=0.05
    )  # points older than 1 s go, checked every 50 ms
    outputs = Outputs(config)  # no wall clock: points carry machine time (here: Unix s)
    assert outputs.store is not None
    try:
        now_s = time.time()
        outputs.sink(record_at(now_s - 30.0))  # a point from 30 s ago …
        outputs.sink(record_at(now_s - 29.0))
        time.sleep(0.1)
        outputs.sink(record_at(time.time()))  # … and one now; the interval has passed
        kept = outputs.store.query("spindle_cycle", "vmc-1")
        assert len(kept) == 1 and kept[0].time_s > now_s - 1.0
        assert outputs.store.expired == 2 * 2  # cycle and temperature points of two cycles
    finally:
        outputs.store.close()


def test_retention_counts_age_in_the_points_own_time_base(tmp_path: Path) -> None:
    """A simulation logs machine time from 0 (1970): its points are seconds old, not decades."""
    config = outputs_config(tmp_path, local_store_retention_days=1.0, retention_interval_s=0.001)
    outputs = Outputs(config)
    assert outputs.store is not None
    try:
        for second in range(0, 600, 60):
            outputs.sink(record_at(float(second)))
            time.sleep(0.002)
        assert len(outputs.store.query("spindle_cycle", "vmc-1")) == 10
        outputs.sink(record_at(86_400.0 + 300.0))  # a day and 5 min later: the first 5 go
        kept = outputs.store.query("spindle_cycle", "vmc-1")
        assert [p.time_s for p in kept] == [300.0, 360.0, 420.0, 480.0, 540.0, 86_700.0]
    finally:
        outputs.store.close()
