"""The objects built at start, kept out of the garbage collector's full passes while running.

A gateway builds its configuration, register maps, models, quality and plausibility
state and the OPC UA address space once, and they live until it stops: at a
thousand machines more than half a million objects. CPython's oldest-generation
collection walks every one of them each time the young objects that survived
have grown by a quarter, which at a 1 s cycle happens every few seconds and
then costs a few hundred ms of CPU and a loop stall as long (timed with
``gc.callbacks`` on the 1000 simulated machines of
``benchmarks/poll_vs_telegraf.py``: about half of the full cycle's CPU).
:func:`frozen_startup_heap` collects once and moves the survivors to the
permanent generation (``gc.freeze``), so the collector only looks at what
the cycles allocate. Nothing else changes: frozen objects are still freed by
reference counting, and leaving the block hands them back to the collector
(``gc.unfreeze``), so a gateway started and stopped in a test leaks nothing.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def frozen_startup_heap() -> Iterator[None]:
    """Run the block with everything alive now frozen (after one full collection)."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
