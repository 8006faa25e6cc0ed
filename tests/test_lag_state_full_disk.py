"""Lag states on a full disk: one warning per episode, not one per minute per machine.

Twenty machines' lag states on a real, filled tmpfs, each saved every minute of
machine time for ten minutes: the loop goes on, the first failed save is named,
the others are not, until space returns (one line says saves work again); a second
episode is named again.
"""

from __future__ import annotations

import errno
import logging
from pathlib import Path

import pytest

from gateway.live.bank.lag_state import EffectStates, WarmLags, lag_file_saved
from tests.test_retention import fill, small_disk

MACHINES = 20
SENSORS = ("T1", "T2")


def minutes(machines: list[EffectStates], start_s: float, count: int) -> None:
    for minute in range(count):
        time_s = start_s + 60.0 * minute
        for states in machines:
            states.advance(time_s, {"T1": 0.1 * minute, "T2": 0.05 * minute}, 4000.0)


def test_a_full_disk_gives_one_lag_state_warning_per_episode(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk", "1m") as disk:
        machines = [
            EffectStates([], disk / f"m{i:02d}-effect-state.json", warm=WarmLags(SENSORS, None))
            for i in range(MACHINES)
        ]
        filler = fill(disk)
        with caplog.at_level(logging.INFO, logger="gateway.live.bank.lag_state"):
            minutes(machines, 0.0, 10)
            failed = [r for r in caplog.records if "cannot save the lag states" in r.message]
            assert len(failed) == 1, [r.message for r in failed][:5]
            assert "No space left on device" in failed[0].message
            filler.unlink()
            minutes(machines, 600.0, 2)
            assert all(states.state_file.exists() for states in machines)
            again = [r for r in caplog.records if "lag states are saved again" in r.message]
            assert len(again) == 1
            filler = fill(disk)  # a second episode is named again
            minutes(machines, 720.0, 3)
        failed = [r for r in caplog.records if "cannot save the lag states" in r.message]
        assert len(failed) == 2
        filler.unlink()


def test_a_folder_still_failing_does_not_silence_a_new_failure_elsewhere(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A state folder on a disk that stays full (its files keep failing, never saved
    again) is one episode; a full disk under another folder is another, named too."""
    first, second = tmp_path / "a", tmp_path / "b"
    full = OSError(errno.ENOSPC, "No space left on device")
    with caplog.at_level(logging.INFO, logger="gateway.live.bank.lag_state"):
        for i in range(3):
            lag_file_saved(first / f"m{i}-effect-state.json", full)
        for i in range(3):
            lag_file_saved(second / f"m{i}-effect-state.json", full)
        for i in range(3):  # the second folder recovers while the first stays full
            lag_file_saved(second / f"m{i}-effect-state.json", None)
    failed = [r.getMessage() for r in caplog.records if "cannot save" in r.getMessage()]
    assert [Path(m.split(":")[0]).parent.name for m in failed] == ["a", "b"], failed
    again = [r.getMessage() for r in caplog.records if "saved again" in r.getMessage()]
    assert len(again) == 1 and "/b/" in again[0], again
    for i in range(3):
        lag_file_saved(first / f"m{i}-effect-state.json", None)
