"""A local store holding days of a few machines' cycles, temperatures and probe values,
written with the store's own writer: the input of the export's streaming tests and of
``benchmarks/export_memory.py``."""

from __future__ import annotations

from pathlib import Path

from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import (
    CYCLE_MEASUREMENT,
    NS_PER_S,
    PROBE_MEASUREMENT,
    TEMPERATURE_MEASUREMENT,
    Point,
)

EPOCH_S = 1.7e9
DAY_S = 86_400
SENSORS = ("T1", "T2", "T3", "ambient")
JITTER_NS = (0, 1_000_000, -2_000_000, 3_000_000, 0, -1_000_000)  # a cycle's time stamp


SHIFT_START_S = 6 * 3600  # the machines run from 06:00 …
SHIFT_S = 8 * 3600  # … for 8 hours a day, with a 20-minute stop half-way (a new run)


def cycle_time_ns(day: int, k: int, cycle_s: float) -> int:
    """The time stamp of cycle ``k`` of ``day``'s shift (a few ms of jitter)."""
    t_s = day * DAY_S + SHIFT_START_S + k * cycle_s + (1_200 if k * cycle_s >= SHIFT_S / 2 else 0)
    return round((EPOCH_S + t_s) * NS_PER_S) + JITTER_NS[k % len(JITTER_NS)]


def cycle_points(machine: str, m: int, i: int, time_ns: int) -> list[Point]:
    """The points of cycle ``i`` of machine number ``m``: speed, four sensors (T2 bad
    now and then, T3 silent now and then), a probe value 0.3 s in (every third cycle
    has none)."""
    tags = {"machine": machine}
    points = [Point(CYCLE_MEASUREMENT, tags, {"speed_rpm": float(1000 * (i // 500 % 9))}, time_ns)]
    for k, sensor in enumerate(SENSORS):
        if sensor == "T3" and i % 50 == 49:
            continue
        quality = "bad" if sensor == "T2" and i % 70 == 69 else "good"
        value = round(20.0 + k + m + 0.5 * ((i // 40 + k) % 23), 4)
        points.append(
            Point(
                TEMPERATURE_MEASUREMENT,
                {**tags, "sensor": sensor, "quality": quality},
                {"value_C": value},
                time_ns,
            )
        )
    if i % 3:
        error = round(5.0 + 0.01 * (i % 997) - m, 4)
        points.append(Point(PROBE_MEASUREMENT, tags, {"error_um": error}, time_ns + 300_000_000))
    return points


def write_long_store(
    path: Path, days: int, machines: tuple[str, ...] = ("m1", "m2"), cycle_s: float = 10.0
) -> Path:
    """Write ``days`` of ``machines``' shifts (one cycle each ``cycle_s``) to a store at
    ``path``, an hour at a time, the periods closed into Parquet parts as the gateway
    closes them."""
    per_hour = round(3600 / cycle_s)
    with LocalStore(path) as store:
        for day in range(days):
            for hour in range(SHIFT_S // 3600):
                ks = range(hour * per_hour, (hour + 1) * per_hour)
                store.write(
                    [
                        p
                        for m, machine in enumerate(machines)
                        for k in ks
                        for p in cycle_points(
                            machine, m, day * 10_000 + k, cycle_time_ns(day, k, cycle_s)
                        )
                    ]
                )
                store.flush()
                store.compact()
    return path
