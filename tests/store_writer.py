"""Write seconds of a small fleet to a local store until killed, saying each one committed.

``python -m tests.store_writer STORE FIRST`` writes second FIRST, FIRST+1, … (each
30 machine-seconds apart, so a 10-minute period closes every 20 seconds and parts are
compacted while it runs): 3 machines' cycle and temperature points, one
:meth:`~gateway.outputs.local_store.LocalStore.flush` (the commit the gateway's thread
makes every second) and one compaction per second (with the merge of a closed day's
parts, as the thread does), then the second's number on stdout
(flushed): that line is the acknowledgement. A parent SIGKILLs it at a random moment.
"""

from __future__ import annotations

import sys

from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import points_from_record
from tests.records import written_record

EPOCH_S = 1.7e9
STEP_S = 30
MACHINES = ("vmc-1", "vmc-2", "vmc-3")
SENSORS = ("T1", "T2", "T3")


def second_points(second: int) -> list:
    """Every point of one written second (the same for a second however often made)."""
    points = []
    for m, machine in enumerate(MACHINES):
        temps = {s: 20.0 + 0.1 * ((second + i + m) % 50) for i, s in enumerate(SENSORS)}
        record = written_record(machine, float(second * STEP_S), temps, 5.0 + 0.01 * (second % 97))
        points += points_from_record(record, EPOCH_S)
    return points


def main() -> None:
    path, first = sys.argv[1], int(sys.argv[2])
    store = LocalStore(path, synchronous="FULL", commit_interval_s=3600.0)
    second = first
    while True:
        store.write(second_points(second))
        store.flush()
        if store.compact():
            store.merge_days()
        print(second, flush=True)
        second += 1


if __name__ == "__main__":
    main()
