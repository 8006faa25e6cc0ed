"""The garbage collector while the gateway runs: startup objects frozen, young passes rarer.

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
the cycles allocate.

The cycles allocate in bursts (every machine of a scheduler slot polls at once,
each with its coroutines, futures and results in flight), so with CPython's
default young-generation threshold of 700 the collector ran about 50 young
passes a second at 1000 machines, each promoting whatever was in flight at that
moment, and those promotions paid for further full passes. While running, the
young threshold is :data:`RUNNING_YOUNG_THRESHOLD` instead: a few young passes a
second and almost no full ones (measured A/B on the poll at 1000 machines: about
a tenth less CPU per request). The cost is memory: at most that many more young
container objects wait for a pass; reference counting still frees everything
not in a reference cycle at once.

Nothing else changes: frozen objects are still freed by reference counting, and
leaving the block hands them back to the collector (``gc.unfreeze``) and restores
the thresholds, so a gateway started and stopped in a test leaks nothing.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

#: Net new container objects between two young-generation passes while running
#: (CPython's default is 700).
RUNNING_YOUNG_THRESHOLD = 10_000


@contextmanager
def frozen_startup_heap() -> Iterator[None]:
    """Run the block with everything alive now frozen (after one full collection) and
    the young-generation threshold at :data:`RUNNING_YOUNG_THRESHOLD`."""
    gc.collect()
    gc.freeze()
    thresholds = gc.get_threshold()
    gc.set_threshold(max(RUNNING_YOUNG_THRESHOLD, thresholds[0]), *thresholds[1:])
    try:
        yield
    finally:
        gc.set_threshold(*thresholds)
        gc.unfreeze()
