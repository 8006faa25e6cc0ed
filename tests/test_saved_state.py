"""State files after a power cut: written durably, and a damaged cold reference refused.

The cold reference is taken once, with the machine cold; a damaged file must not be
replaced by a new first reading from a machine that may be warm.
"""

from __future__ import annotations

import json
import logging
import os
import stat
from pathlib import Path

import pytest

from gateway.live.reference import TemperatureReference, read_saved_reference
from gateway.outputs.heartbeat import write_heartbeat
from models.json_files import write_json_atomic


def test_the_cold_reference_is_saved_once_and_read_back(tmp_path: Path) -> None:
    state = tmp_path / "bench-1-reference.json"
    cold = TemperatureReference("first-reading", {}, state)
    cold.observe({"T1": 20.5, "T2": 21.0})
    cold.observe({"T1": 35.0, "T3": 22.0})  # T1 keeps its first reading
    assert read_saved_reference(state) == {"T1": 20.5, "T2": 21.0, "T3": 22.0}
    restarted = TemperatureReference("first-reading", {}, state)
    assert restarted.rises_C({"T1": 30.5, "T2": 21.0}, ("T1", "T2")) == [10.0, 0.0]


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"", "Expecting value: line 1 column 1"),  # a power cut before the data reached disk
        (b'{"reference_C": {"T1": 20.5', "Expecting ',' delimiter"),  # cut mid-write
        (b'{"reference_C": {"T1": 2\xff0.5}}', "codec can't decode byte 0xff"),
        (b"{}", "missing 'reference_C'"),
        (b'{"reference_C": [20.5]}', "'reference_C' is not an object"),
        (b'{"reference_C": {"T1": "warm"}}', "could not convert string to float"),
        (b'{"reference_C": {"T1": NaN}}', "sensor T1: expected a temperature in °C"),
        (b'{"reference_C": {"T1": 1e308}}', "from -60 to 400, found 1e+308"),
    ],
)
def test_a_damaged_reference_is_refused_naming_the_file_and_what_to_do(
    tmp_path: Path, content: bytes, reason: str
) -> None:
    state = tmp_path / "bench-1-reference.json"
    state.write_bytes(content)
    with pytest.raises(ValueError) as refused:
        TemperatureReference("first-reading", {}, state)
    message = str(refused.value)
    assert message.startswith(f"{state}: the machine's saved cold reference is unreadable (")
    assert reason in message
    assert message.endswith(
        "restore the file, or delete it to take a new reference with the machine cold"
    )
    assert state.read_bytes() == content  # left as it was, for whoever restores it


def test_a_fixed_reference_never_reads_the_saved_file(tmp_path: Path) -> None:
    state = tmp_path / "bench-1-reference.json"
    state.write_bytes(b"")
    fixed = TemperatureReference("fixed", {"T1": 20.0}, state)
    assert fixed.rises_C({"T1": 25.0}, ("T1",)) == [5.0]


def synced(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Record what each os.fsync call synced: 'file' or 'folder'."""
    calls: list[str] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        calls.append("folder" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return calls


def test_state_files_reach_the_disk_before_and_after_the_rename(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = synced(monkeypatch)
    path = write_json_atomic(tmp_path / "state" / "x.json", {"a": 1})
    assert calls == ["file", "folder"]  # the data before the rename, the rename after it
    assert json.loads(path.read_text(encoding="utf-8")) == {"a": 1}
    TemperatureReference("first-reading", {}, tmp_path / "r.json").observe({"T1": 20.0})
    assert calls[2:] == ["file", "folder"]


def test_the_heartbeat_rewritten_every_cycle_is_not_synced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = synced(monkeypatch)
    path = write_heartbeat(tmp_path, "bench-1", 60.0, 1, wall_time=1.0e9)
    assert calls == [] and json.loads(path.read_text(encoding="utf-8"))["machine"] == "bench-1"


@pytest.mark.parametrize("threaded", [False, True], ids=["in-place", "writer-thread"])
def test_a_full_disk_keeps_the_cold_reference_in_memory_and_saves_it_once_space_returns(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, threaded: bool
) -> None:
    """Saved in place, or by a writer thread as in a running gateway (each cycle's save
    waited for here, so the test knows its outcome before the next cycle)."""
    from gateway.process.file_writer import FileWriter
    from tests.test_retention import fill, small_disk

    writer = FileWriter("test-state-writer", durable=True) if threaded else None

    def cycle(readings: dict[str, float]) -> None:
        reference.observe(readings)
        assert writer is None or writer.flush(10.0)

    with small_disk(tmp_path / "disk", "1m") as disk:
        state = disk / "bench-1-reference.json"
        filler = fill(disk)
        reference = TemperatureReference("first-reading", {}, state, writer=writer)
        with caplog.at_level(logging.INFO, logger="gateway.live.reference"):
            for n in range(5):  # the loop goes on: nothing is raised
                cycle({"T1": 20.5 + n, "T2": 21.0})
            assert reference.values_C == {"T1": 20.5, "T2": 21.0} and not state.exists()
            failed = [r for r in caplog.records if "cannot save the cold reference" in r.message]
            assert len(failed) == 1 and "No space left on device" in failed[0].message
            filler.unlink()
            cycle({"T1": 30.0, "T2": 31.0})
        assert read_saved_reference(state) == {"T1": 20.5, "T2": 21.0}
        assert "the cold reference is saved now" in caplog.text


def test_a_full_disk_leaves_the_old_file_whole_and_the_error_names_the_file(
    tmp_path: Path,
) -> None:
    from models.json_files import atomic_text
    from tests.test_retention import fill, small_disk

    with small_disk(tmp_path / "disk", "1m") as disk:
        target = disk / "runs.csv"
        with atomic_text(target) as out:
            out.write("run,time_s\n")
        fill(disk)
        with pytest.raises(OSError) as refused, atomic_text(target) as out:
            out.write("x" * 100_000)
        assert refused.value.filename == str(target)
        assert "No space left on device" in str(refused.value)
        assert target.read_text(encoding="utf-8") == "run,time_s\n"  # as it was
        assert sorted(p.name for p in disk.iterdir()) == ["filler", "runs.csv"]  # no temp


def test_simulate_record_on_a_full_disk_says_so_and_leaves_no_half_file(tmp_path: Path) -> None:
    from tests.cli import gateway_in_process
    from tests.test_retention import fill, small_disk

    with small_disk(tmp_path / "disk", "64k") as disk:
        fill(disk)
        result = gateway_in_process("simulate", "--record", disk / "runs.csv")
        assert result.returncode == 2, result.stdout + result.stderr
        assert result.stderr.splitlines() == [
            f"error: [Errno 28] No space left on device: '{disk / 'runs.csv'}'"
        ]
        assert sorted(p.name for p in disk.iterdir()) == ["filler"]
