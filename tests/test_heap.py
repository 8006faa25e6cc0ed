"""The collector's settings while the gateway runs (gateway.process.gc_tuning)."""

from __future__ import annotations

import gc

from gateway.process.gc_tuning import RUNNING_YOUNG_THRESHOLD, frozen_startup_heap


def test_the_running_block_freezes_startup_objects_and_raises_the_young_threshold() -> None:
    before = gc.get_threshold()
    with frozen_startup_heap():
        assert gc.get_freeze_count() > 0
        assert gc.get_threshold()[0] == max(RUNNING_YOUNG_THRESHOLD, before[0])
        assert gc.get_threshold()[1:] == before[1:]
    assert gc.get_threshold() == before
    assert gc.get_freeze_count() == 0
