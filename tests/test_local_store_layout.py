"""The local store's typed layout: SIGKILLs mid-write, conversion of the JSON layout, reads.

Kills are real ``SIGKILL`` signals sent to a real writer process
(:mod:`tests.store_writer`) at random moments, while it commits seconds and compacts
closed periods into Parquet parts; after each, the store is opened as ``export``
opens it (a damaged file is refused, never set aside) and every second the writer
acknowledged must be there, whole and once. The conversion test writes a store with
the earlier JSON layout (:mod:`tests.json_layout_store`) and compares every point and
the ``export`` CSV read from both.
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from gateway.offline.export import export_runs
from gateway.outputs import local_store
from gateway.outputs.local_store import DAY_NS, LocalStore, history_folder, parts_folder
from gateway.outputs.points import Point, probe_point
from tests.json_layout_store import JsonLocalStore
from tests.store_writer import EPOCH_S, STEP_S, second_points

KILLS = 50


def _second_of(point: Point) -> int:
    return round((point.time_ns / 1e9 - EPOCH_S) / STEP_S)


def _stored_seconds(path: Path) -> Counter:
    """How many points each stored second holds (opened as export opens a store)."""
    with LocalStore(path, set_aside_damaged=False) as store:
        found: Counter = Counter()
        for measurement in ("spindle_cycle", "spindle_temperature"):
            found.update(_second_of(p) for p in store.query(measurement))
        return found


def _run_until_killed(path: Path, first: int, rng: random.Random) -> list[int]:
    """Start a writer at second ``first``, SIGKILL it after a random moment of
    writing; the seconds it acknowledged."""
    writer = subprocess.Popen(
        [sys.executable, "-m", "tests.store_writer", str(path), str(first)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert writer.stdout is not None
    acked = [int(writer.stdout.readline())]  # it writes: now let it run a random while
    time.sleep(rng.uniform(0.0, 0.4))
    writer.send_signal(signal.SIGKILL)
    rest, _ = writer.communicate(timeout=30)
    assert writer.returncode == -signal.SIGKILL
    return acked + [int(line) for line in rest.split()]


def test_sigkill_mid_write_keeps_every_acknowledged_second(tmp_path: Path) -> None:
    path = tmp_path / "points.sqlite"
    per_second = len(second_points(0))
    rng = random.Random(7)
    acked: list[int] = []
    for _ in range(KILLS):
        first = max(acked, default=-1) + 1
        acked += _run_until_killed(path, first, rng)
        stored = _stored_seconds(path)
        missing = [s for s in acked if stored[s] != per_second]
        assert not missing, f"acknowledged seconds not stored whole: {missing[:5]}"
        assert all(n == per_second for n in stored.values()), "a second stored twice"
    assert len(acked) > 2 * KILLS  # the kills fell on a writer at work
    LocalStore(path).close()  # the writer's next start removes a crash's leftovers
    names = {p.name for p in parts_folder(path).iterdir()}
    assert names and all(n.endswith(".parquet") for n in names)


def _old_layout_points() -> list[Point]:
    """A few hours of two machines as the gateway logs them, plus the odd points: a
    sensor gone bad (a reason, no value), probes, a tag and a field outside the typed
    columns, an integer where a float usually is."""
    points = []
    for second in range(0, 3 * 3600, 7):
        points += second_points(second)
    bad = {"machine": "vmc-1", "sensor": "T2", "quality": "bad"}
    points.append(Point("spindle_temperature", bad, {"reason": "open circuit"}, points[50].time_ns))
    for k in range(40):
        points.append(probe_point("vmc-1", k * 30 * STEP_S + 1.0, 3.0 + 0.1 * k, EPOCH_S))
    odd_tags = {"machine": "vmc-2", "line": "B"}
    points.append(Point("spindle_cycle", odd_tags, {"speed_rpm": 1500, "note": "x"}, 12345))
    return points


def test_a_json_layout_store_is_converted_with_every_point_kept(tmp_path: Path) -> None:
    path = tmp_path / "points.sqlite"
    with JsonLocalStore(path) as old:
        old.write(_old_layout_points())
        count = len(old)
        before = {
            m: old.query(m) for m in ("spindle_cycle", "spindle_temperature", "spindle_probe")
        }
        export_runs(old, "vmc-1", None, None, tmp_path / "old.csv", epoch_s=EPOCH_S)
    with LocalStore(path) as new:
        assert new.migrated == count and len(new) == count
        for measurement, points in before.items():
            key = lambda p: (p.time_ns, sorted(p.tags.items()))  # noqa: E731
            assert sorted(new.query(measurement), key=key) == sorted(points, key=key)
        export_runs(new, "vmc-1", None, None, tmp_path / "new.csv", epoch_s=EPOCH_S)
    assert (tmp_path / "new.csv").read_text() == (tmp_path / "old.csv").read_text()
    with LocalStore(path) as again:  # converted once: nothing left to convert
        assert again.migrated == count and len(again) == count


def test_retention_keeps_exactly_the_points_after_the_cutoff(tmp_path: Path) -> None:
    """Age cut through the middle of a Parquet part: the part is trimmed, not dropped."""
    with LocalStore(tmp_path / "points.sqlite", retention_s=1000 * STEP_S) as store:
        for second in range(0, 2000):
            store.write(second_points(second))
        now_ns = second_points(2000)[0].time_ns
        store.compact(now_ns)
        assert len(list(parts_folder(store.path).iterdir())) > 5  # periods closed into parts
        store.enforce_retention(now_ns)
        seconds = Counter(_second_of(p) for p in store.query("spindle_cycle"))
        assert min(seconds) == 1000 and max(seconds) == 1999 and len(seconds) == 1000


def test_the_minute_history_outlives_the_seconds_and_goes_last_at_the_cap(
    tmp_path: Path,
) -> None:
    """Per-minute min/mean/max from the 1-s points; kept after the points age out; at the
    size cap the 1-s parts go first, then the oldest minutes."""
    path = tmp_path / "points.sqlite"
    with LocalStore(path, retention_s=100 * STEP_S) as store:
        for second in range(400):  # 400 × 30 s: 200 minutes, 20 parts
            store.write(second_points(second))
        store.compact(second_points(440)[0].time_ns)  # every period closed
        cycles = store.query("spindle_cycle", machine="vmc-2")
        minute = store.history("spindle_cycle", machine="vmc-2")
        assert len(minute) == len({p.time_ns // 60_000_000_000 for p in cycles})
        first = [p.fields["applied_um"] for p in cycles[:2]]  # two cycles in the first minute
        assert minute[0]["samples"] == 2
        assert minute[0]["applied_um_min"] == min(first)
        assert minute[0]["applied_um_max"] == max(first)
        assert abs(minute[0]["applied_um_mean"] - sum(first) / 2) < 1e-12
        store.enforce_retention(second_points(400)[0].time_ns)
        assert len(store.query("spindle_cycle")) == 100 * 3  # the last 100 seconds only
        assert len(store.history("spindle_cycle", machine="vmc-2")) == len(minute)
        minutes_bytes = store.used_bytes()
    with LocalStore(path, max_bytes=minutes_bytes // 2) as small:
        small.enforce_retention(second_points(400)[0].time_ns, budget_s=10.0)
        assert small.query("spindle_cycle") == []  # the 1-s points went first
        kept = small.history("spindle_cycle", machine="vmc-2")
        assert 0 < len(kept) < len(minute) and kept[-1] == minute[-1]  # then the oldest minutes
        assert small.used_bytes() <= 0.98 * small.max_bytes


def test_another_process_reads_while_the_writer_closes_periods(tmp_path: Path) -> None:
    """``export`` runs beside the gateway: every read sees whole seconds, never fewer
    points than the read before, while the writer compacts periods into parts."""
    path = tmp_path / "points.sqlite"
    writer = subprocess.Popen(
        [sys.executable, "-m", "tests.store_writer", str(path), "0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert writer.stdout is not None
    try:
        writer.stdout.readline()
        seen = []
        expected = Counter(p.measurement for p in second_points(0))
        for _ in range(15):
            with LocalStore(path, set_aside_damaged=False) as store:
                for measurement, n in expected.items():  # each read is one snapshot
                    stored = Counter(_second_of(p) for p in store.query(measurement))
                    assert set(stored.values()) == {n}, (measurement, stored)
                seen.append(sum(stored.values()))
            time.sleep(0.1)
    finally:
        writer.send_signal(signal.SIGKILL)
        writer.communicate(timeout=30)
    assert seen == sorted(seen) and seen[-1] > seen[0]
    assert len(list(parts_folder(path).glob("*.parquet"))) > 2  # periods closed meanwhile


def test_a_closed_day_is_merged_into_one_part_with_every_point(tmp_path: Path) -> None:
    with LocalStore(tmp_path / "points.sqlite") as store:
        for second in range(0, 6300, 3):  # 6300 × 30 s: two days and more
            store.write(second_points(second))
        now_ns = second_points(6300)[0].time_ns
        store.compact(now_ns)  # each write closed its periods and merged closed days
        store.merge_days(now_ns)
        days = Counter(
            int(p.name.split("-")[0]) // DAY_NS for p in parts_folder(store.path).iterdir()
        )
        closed = [n for day, n in days.items() if day < (now_ns - 60 * 10**9) // DAY_NS]
        assert len(closed) >= 2 and set(closed) == {1}  # a closed day: one part
        assert sum(days.values()) < 316 / 10  # written as 316 parts of 10 minutes
        seconds = Counter(_second_of(p) for p in store.query("spindle_temperature"))
        assert set(seconds) == set(range(0, 6300, 3)) and set(seconds.values()) == {9}
        assert len(store) == 2100 * 12


def _bytes_written() -> int:
    """Bytes this process has passed to ``write()`` (``wchar`` of /proc/self/io)."""
    with open("/proc/self/io") as stream:
        return next(int(line.split()[1]) for line in stream if line.startswith("wchar:"))


def test_each_second_writes_about_what_the_store_keeps(tmp_path: Path) -> None:
    """20 machines' simulated cycles committed once a second (fsynced, as the gateway
    commits) for a 10-minute period, closed into its part: every byte written — the
    open period's appends, the part and its per-minute history — at most 3 times
    what the part and history keep (an open period in SQLite wrote 100 times more)."""
    from benchmarks.store_engines import Stream, stream_ns

    stream = Stream(20)
    seconds = [stream.second(s) for s in range(600)]
    before = _bytes_written()
    path = tmp_path / "points.sqlite"
    with LocalStore(path, synchronous="FULL", commit_interval_s=3600.0) as store:
        for batches in seconds:
            for points in batches:
                store.write(points)
            store.flush()  # the commit thread's once a second
        store.compact(stream_ns(600 + 700))
        assert len(store) == 20 * 600 * 11
    written = _bytes_written() - before
    kept = sum(
        p.stat().st_size
        for folder in (tmp_path / "points.sqlite.parts", tmp_path / "points.sqlite.history")
        for p in folder.iterdir()
    )
    assert not list((tmp_path / "points.sqlite.open").iterdir())  # the period closed
    assert written <= 3 * kept, f"{written} bytes written for {kept} kept"


def test_a_day_of_large_parts_is_left_as_it_is(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Parts of at least :data:`MERGE_BELOW_BYTES` on average compress as well alone:
    their day is not rewritten, every point still read."""
    monkeypatch.setattr(local_store, "MERGE_BELOW_BYTES", 1)  # every part counts as large
    with LocalStore(tmp_path / "points.sqlite") as store:
        for second in range(0, 3000, 3):  # 3000 × 30 s: a day and more
            store.write(second_points(second))
        now_ns = second_points(3000)[0].time_ns
        store.compact(now_ns)
        store.merge_days(now_ns)
        parts = list(parts_folder(store.path).iterdir())
        assert len(parts) == 3000 * 30 // 600  # one part a 10-minute period
        assert len(list(history_folder(store.path).iterdir())) == len(parts)
        seconds = Counter(_second_of(p) for p in store.query("spindle_temperature"))
        assert set(seconds) == set(range(0, 3000, 3)) and set(seconds.values()) == {9}


def test_a_record_cut_short_is_never_read_and_the_writer_cuts_it_off(tmp_path: Path) -> None:
    """A crash mid-append leaves part of a record at a segment's end (here: the first
    half of the next second's record, then a whole record with one byte changed):
    readers stop before it, and the next writer appends after the last whole record."""
    path = tmp_path / "points.sqlite"
    with LocalStore(path, synchronous="FULL", commit_interval_s=3600.0) as store:
        for second in range(5):
            store.write(second_points(second))
            store.flush()
    (segment,) = (tmp_path / "points.sqlite.open").iterdir()
    whole = segment.read_bytes()
    with LocalStore(tmp_path / "other.sqlite", synchronous="FULL") as other:
        other.write(second_points(5))
    (record,) = (tmp_path / "other.sqlite.open").iterdir()
    torn = record.read_bytes()
    for tail in (torn[: len(torn) // 2], torn[:-1] + bytes([torn[-1] ^ 1])):
        segment.write_bytes(whole + tail)
        assert set(_stored_seconds(path)) == set(range(5))  # the tail is not read
    with LocalStore(path, synchronous="FULL") as store:
        store.write(second_points(6))
    assert segment.read_bytes().startswith(whole)  # the tail cut off, the record after
    assert set(_stored_seconds(path)) == {0, 1, 2, 3, 4, 6}
