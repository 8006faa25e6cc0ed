"""A damaged log file (local store, disk buffer) is kept aside, never thrown away, and
never stops the gateway; a reader refuses it plainly; other SQLite failures still raise."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import Point

GARBAGE = b"this was a points file until a flash card lost a block\x00\xff" * 100


def points(n: int, start_ns: int = 1_700_000_000_000_000_000) -> list[Point]:
    return [
        Point("spindle", {"machine": "m1"}, {"T1_C": 20.0 + k}, start_ns + k * 1_000_000_000)
        for k in range(n)
    ]


def aside_of(path: Path) -> Path:
    (aside,) = path.parent.glob(f"{path.name}.unreadable-*[0-9Z]")
    return aside


def test_a_local_store_that_is_not_a_database_is_kept_aside_and_a_new_one_started(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "points.sqlite"
    path.write_bytes(GARBAGE)
    Path(f"{path}-wal").write_bytes(b"old wal")
    store = LocalStore(path)
    try:
        aside = aside_of(path)
        assert store.set_aside_as == aside
        assert aside.read_bytes() == GARBAGE  # kept byte for byte
        assert Path(f"{aside}-wal").read_bytes() == b"old wal"  # with its companion
        assert store.write(points(3))
        assert len(store.query("spindle", "m1")) == 3
    finally:
        store.close()
    assert f"{path}: not a readable SQLite database (file is not a database)" in caplog.text
    assert f"kept as {aside}, a new one started" in caplog.text


def test_a_good_store_opens_as_it_was(tmp_path: Path) -> None:
    path = tmp_path / "points.sqlite"
    first = LocalStore(path)
    first.write(points(2))
    first.close()
    again = LocalStore(path)
    try:
        assert again.set_aside_as is None and len(again.query("spindle", "m1")) == 2
    finally:
        again.close()


def test_a_disk_buffer_with_a_damaged_image_is_kept_aside_and_buffers_on(tmp_path: Path) -> None:
    path = tmp_path / "buffer.sqlite"
    buffer = PointBuffer(path)
    buffer.append(points(50))
    buffer.close()
    image = bytearray(path.read_bytes())
    image[100:4096] = b"\xa5" * (4096 - 100)  # the header's tail and the schema page
    path.write_bytes(bytes(image))
    reopened = PointBuffer(path)
    try:
        assert reopened.set_aside_as is not None
        assert reopened.set_aside_as.read_bytes() == bytes(image)
        assert len(reopened) == 0
        reopened.append(points(4))
        assert [p.time_ns for _, p in reopened.peek(10)] == [p.time_ns for p in points(4)]
    finally:
        reopened.close()


def test_other_sqlite_failures_are_raised_and_nothing_is_moved(tmp_path: Path) -> None:
    path = tmp_path / "points.sqlite"
    path.mkdir()  # a folder where the file should be: SQLite cannot open it
    with pytest.raises(sqlite3.OperationalError, match="unable to open database file"):
        LocalStore(path)
    assert path.is_dir() and list(tmp_path.iterdir()) == [path]


def test_a_reader_refuses_a_damaged_store_and_leaves_it_where_it_is(tmp_path: Path) -> None:
    path = tmp_path / "points.sqlite"
    path.write_bytes(GARBAGE)
    wal = Path(f"{path}-wal")
    wal.write_bytes(b"old wal")
    with pytest.raises(ValueError, match=r"points\.sqlite: not a readable SQLite database"):
        LocalStore(path, set_aside_damaged=False)
    assert path.read_bytes() == GARBAGE and wal.read_bytes() == b"old wal"
    assert sorted(tmp_path.iterdir()) == [path, wal]
