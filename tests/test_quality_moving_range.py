"""The stuck check's "others moved" test: exact running extremes, cost independent of stuck_s.

A stopped machine holds its temperatures still for hours, so every cycle every
sensor asks how far each other sensor moved since its own constant run began.
``_MovingRange`` answers from monotonic queues; these tests hold it to the plain
scan over the kept values and show the work per cycle no longer grows with
``stuck_s``.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

import gateway.live.quality as quality
from gateway.limits import QualityLimits
from gateway.live.quality import Quality, QualityMonitor


@pytest.mark.parametrize("seed", range(8))
def test_moving_range_equals_the_plain_scan(seed):
    rng = np.random.default_rng(seed)
    keep_s = float(rng.choice([3.0, 30.0, 200.0]))
    moving = quality._MovingRange()
    kept: list[tuple[float, float]] = []
    now_s, value = 0.0, 20.0
    for _ in range(2000):
        now_s += float(rng.choice([0.1, 1.0, 1.0, 7.0, 60.0]))
        kind = rng.random()
        if kind < 0.4:
            pass  # the same value again (a register that does not move)
        elif kind < 0.8:
            value += float(rng.choice([-0.1, 0.1, 0.05]))
        else:
            value = float(rng.uniform(10.0, 40.0))
        moving.push(now_s, value, now_s - keep_s)
        kept = [(t, v) for t, v in [*kept, (now_s, value)] if t >= now_s - keep_s]
        for since_s in (now_s - keep_s - 5.0, *rng.uniform(now_s - keep_s, now_s + 1.0, 4)):
            values = [v for t, v in kept if t >= since_s]
            plain = max(values) - min(values) if values else 0.0
            assert moving.since(float(since_s)) == plain, (now_s, since_s)
        for t, _ in kept:  # the kept times themselves, where ties decide
            values = [v for u, v in kept if u >= t]
            assert moving.since(t) == max(values) - min(values)


def test_a_shorter_stuck_window_looks_only_since_its_own_run_began():
    """T1 (stuck_s 10 s) is judged on T2's moves since T1 froze, within T2's longer kept span."""
    limits = {"T1": QualityLimits(stuck_s=10.0), "T2": QualityLimits(stuck_s=100.0)}
    monitor = QualityMonitor(["T1", "T2"], limits)
    for t in range(0, 40):  # T2 rises 2 °C in the first 20 s, then holds; T1 frozen from 25 s
        t2 = 30.0 + min(t, 20) * 0.1
        t1 = 25.0 + min(t, 25) * 0.1
        checks = monitor.check(float(t), {"T1": (t1, 0), "T2": (t2, 0)})
    assert checks["T1"].quality is Quality.GOOD  # T2 moved long before T1's run began
    for t in range(40, 60):  # now T2 moves again while T1 stays frozen
        checks = monitor.check(float(t), {"T1": (27.5, 0), "T2": (32.0 + (t - 39) * 0.1, 0)})
    assert checks["T1"].quality is Quality.BAD
    assert checks["T1"].reason is not None and checks["T1"].reason.startswith("stuck at 27.5")


def _lines_per_check(stuck_s: float, checks: int = 50) -> float:
    """Python lines run in quality.py per check of a steady 6-sensor machine after stuck_s."""
    sensors = [f"T{i}" for i in range(6)]
    monitor = QualityMonitor(sensors, QualityLimits(stuck_s=stuck_s))
    readings = {s: (20.0 + i, 0) for i, s in enumerate(sensors)}
    start = int(stuck_s) + 5
    for t in range(start):
        monitor.check(float(t), readings)
    counted = 0
    here = quality.__file__

    def tracer(frame, event, arg):
        nonlocal counted
        if frame.f_code.co_filename != here:
            return None
        counted += event == "line"
        return tracer

    previous = sys.gettrace()
    sys.settrace(tracer)
    try:
        for t in range(start, start + checks):
            verdicts = monitor.check(float(t), readings)
    finally:
        sys.settrace(previous)
    assert all(v.quality is Quality.GOOD for v in verdicts.values())  # constant is not stuck
    return counted / checks


def test_steady_sensors_cost_the_same_whatever_stuck_s():
    short, long = _lines_per_check(10.0), _lines_per_check(3600.0)
    assert long <= 1.2 * short, (short, long)
