"""The state folder's lock: held while a gateway runs, free again when it ends."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from gateway.process.instance_lock import StateDirInUseError, hold_state_dir


def test_a_held_state_dir_is_refused_naming_the_holder_then_free_after(tmp_path: Path) -> None:
    state = tmp_path / "state" / "not-yet-made"
    with hold_state_dir(state) as lock:
        assert lock.read_text(encoding="ascii") == f"{os.getpid()}\n"
        # flock locks belong to the open file: a second open in this process conflicts too.
        refused = rf"another gateway \(pid {os.getpid()}\)"
        with pytest.raises(StateDirInUseError, match=refused), hold_state_dir(state):
            pass
    with hold_state_dir(state):  # released on leaving the block
        pass


def test_a_left_over_lock_file_with_anything_in_it_does_not_block(tmp_path: Path) -> None:
    (tmp_path / "gateway.lock").write_bytes(b"\x00stale 99999 \xff")
    with hold_state_dir(tmp_path) as lock:
        assert lock.read_text(encoding="ascii") == f"{os.getpid()}\n"


def test_the_lock_is_taken_on_a_full_disk(tmp_path: Path) -> None:
    from tests.test_retention import fill, small_disk

    with small_disk(tmp_path / "disk", "1m") as disk:
        (disk / "state").mkdir()
        fill(disk)
        with hold_state_dir(disk / "state") as lock:
            assert lock.exists()  # held, though there was no room to write the pid
            refused = r"another gateway \(pid unknown\)"
            with pytest.raises(StateDirInUseError, match=refused), hold_state_dir(disk / "state"):
                pass
