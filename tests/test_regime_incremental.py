"""The regime selector's running aggregates give exactly what ``classify`` gives.

``RegimeSelector`` classifies from a sliding max/min and a stopped count instead
of scanning the window each cycle; ``classify`` stays the plain reference. Over
random speed histories (stops, steps, jitter within and beyond the tolerance,
bands, reverse rotation, irregular cycle times, repeated times and gaps) the two
must agree at every step, and the per-update work must not grow with the window.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator

import numpy as np
import pytest

import models.online.regime_rules as regime_rules
from models.online.regime_rules import (
    STOPPED_BELOW_RPM,
    RegimeRules,
    RegimeSelector,
    Selection,
    SpeedBand,
    classify,
)

BANDS = (SpeedBand("low", 0.0, 3000.0), SpeedBand("mid", 3000.0, 6000.0))


class PlainSelector(RegimeSelector):
    """The selector as it classified before: ``classify`` over the kept history."""

    def _classify(self, now_s: float) -> str:
        return classify(self._history, now_s, self.rules)


def _cycle_times(rng: np.random.Generator, n: int, cycle_s: float) -> Iterator[float]:
    """Regular, jittered, repeated (dt 0) and gapped cycle times."""
    now_s = float(rng.uniform(-50.0, 50.0))
    for _ in range(n):
        yield now_s
        kind = rng.random()
        if kind < 0.05:
            now_s += 0.0  # the same time again
        elif kind < 0.08:
            now_s += float(rng.uniform(5.0, 80.0)) * cycle_s  # a gap
        elif kind < 0.5:
            now_s += cycle_s * float(rng.uniform(0.3, 1.7))
        else:
            now_s += cycle_s


def _speeds(rng: np.random.Generator, n: int, tolerance_rpm: float) -> Iterator[float]:
    """Segments of stops, steady speeds with jitter within/beyond tolerance, and steps."""
    left = 0
    level, jitter = 0.0, 0.0
    for _ in range(n):
        if left == 0:
            left = int(rng.integers(1, 60))
            kind = rng.random()
            if kind < 0.25:
                level, jitter = 0.0, float(rng.choice([0.0, 0.3, 0.99, 1.0]))  # stopped
            else:
                level = float(rng.choice([500.0, 2999.0, 3000.0, 4500.0, 6000.0, 8000.0]))
                level *= float(rng.choice([1.0, -1.0]))  # M03 or M04
                jitter = float(rng.choice([0.0, 0.4, 0.5, 0.6])) * tolerance_rpm
        left -= 1
        speed = level + float(rng.uniform(-jitter, jitter))
        if rng.random() < 0.02:
            speed = float(rng.choice([0.0, -0.0, STOPPED_BELOW_RPM, level + tolerance_rpm]))
        yield speed


@pytest.mark.parametrize("seed", range(12))
def test_incremental_classification_equals_classify_at_every_step(seed):
    rng = np.random.default_rng(seed)
    cycle_s = float(rng.choice([0.1, 1.0, 2.5]))
    rules = RegimeRules(
        window_s=float(rng.choice([5.0, 20.0, 60.0])) * cycle_s,
        constant_tolerance_rpm=float(rng.choice([0.0, 50.0, 150.0])),
        min_dwell_s=float(rng.choice([0.0, 10.0])) * cycle_s,
        bands=BANDS if seed % 2 else (),
        models={"variable": "v", "constant": "c"},
    )
    new, plain = RegimeSelector(rules), PlainSelector(rules)
    strictly_increasing = seed % 3 == 0
    full: list[tuple[float, float]] = []
    seen: set[str] = set()
    n = 3000
    times = _cycle_times(rng, n, cycle_s)
    speeds = _speeds(rng, n, rules.constant_tolerance_rpm)
    for i, (now_s, speed) in enumerate(zip(times, speeds, strict=True)):
        if strictly_increasing:
            now_s += i * 1e-3 * cycle_s
        got: Selection = new.update(now_s, speed)
        assert got == plain.update(now_s, speed), f"step {i} at {now_s} s"
        label = new._classify(now_s)
        assert label == classify(new._history, now_s, rules), f"step {i} at {now_s} s"
        full.append((now_s, speed))
        if strictly_increasing:  # the kept history is all classify needs of the whole one
            assert label == classify(full, now_s, rules), f"step {i} at {now_s} s"
        seen.add(label.split("/")[0])
    assert seen == {"variable", "constant", "idle"}  # every branch was exercised
    assert new.switches == plain.switches


def _lines_per_update(history_s: float, updates: int = 200) -> float:
    """Python lines executed in regime_rules per update, once ``history_s`` of 1 s cycles ran."""
    rules = RegimeRules(window_s=history_s)
    selector = RegimeSelector(rules)
    rng = np.random.default_rng(1)
    speeds = 6000.0 + rng.uniform(-40.0, 40.0, int(history_s) + updates + 2)
    for t in range(int(history_s) + 2):
        selector.update(float(t), float(speeds[t]))
    counted = 0
    here = regime_rules.__file__

    def tracer(frame, event, arg):
        nonlocal counted
        if frame.f_code.co_filename != here:
            return None
        if event == "line":
            counted += 1
        return tracer

    previous = sys.gettrace()
    sys.settrace(tracer)
    try:
        for t in range(int(history_s) + 2, int(history_s) + 2 + updates):
            selector.update(float(t), float(speeds[t]))
    finally:
        sys.settrace(previous)
    return counted / updates


def test_update_work_does_not_grow_with_the_window():
    short, long = _lines_per_update(10.0), _lines_per_update(3600.0)
    assert long <= 1.2 * short, (short, long)
