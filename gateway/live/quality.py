"""Per-sensor quality flag, decided every cycle before any value reaches a model.

A thermal-error model trusts every input it is given: one open Pt100 reading
850 °C, or a transmitter frozen at its last value while the spindle heats up,
silently turns into tens of µm of wrong compensation. So each cycle every sensor
is checked, in this order, and the first failed check is the reason it is BAD:

1. transmitter status: any non-zero code is a fault the module itself reports;
2. the value is a finite number inside [min_C, max_C];
3. rate: the change since the *last good* value, per second, is at most
   ``max_rate_C_per_s``. Comparing with the last good value (not the previous
   sample) means a spike is judged against the pre-spike value, and so is the
   sample after it: the spike never becomes the reference;
4. stuck: the value moved by no more than ``stuck_band_C`` for ``stuck_s`` while
   at least one other sensor of the machine moved by more than 1 °C in that
   time. A constant value alone proves nothing (a cold machine is constant);
   a constant value on a machine that is heating or cooling does;
5. stale: no value at all for more than ``stale_s`` since the last good one.

A single missed read (value ``None`` within ``stale_s``) is not a new value: the
sensor keeps the result of its previous check and nothing is counted.

Hysteresis: after any BAD check a sensor needs ``recover_cycles`` consecutive
good checks before it is GOOD again, so a loose contact that flickers between
good and bad never flaps the model's inputs in and out. A sensor that has never
produced a value starts BAD ("no value yet"), so the same rule applies to it.

Plausibility (:mod:`gateway.live.plausibility`), when the monitor is given one: after
these checks, the sensors that passed them are compared with each other
through the relation learned at fit time. A sensor that disagrees is held BAD
("implausible: …") until it has agreed again for ``plausibility_recover_s``;
the hold overrides a GOOD verdict, while a sensor failing one of the checks
above keeps that more specific reason. :meth:`QualityMonitor.mark_implausible`
lets the loop hold the sensor its prediction rate bound blames.

Everything is plain numbers and machine time in seconds passed in by the caller;
no I/O happens here.

The "others moved" test of rule 4 runs every cycle for every sensor whose value
has stayed within the band for ``stuck_s`` while the others did not move: the
normal state of a stopped machine, whose temperatures hold still for hours.
Each sensor therefore keeps the running extremes of its last ``stuck_s`` of
values (:class:`_MovingRange`) and answers "how far did it move since t" in
O(log n) instead of scanning them: the scan cost grows with ``stuck_s`` (900
values at the default and a 1 s cycle, for every pair of sensors, every cycle).
A stopped machine's 6 steady sensors took 1.5 ms a check once ``stuck_s`` had
passed, and take 19 µs (``benchmarks/cycle_cost_over_time.py``, CPU time).
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from operator import itemgetter
from typing import TYPE_CHECKING

from gateway.limits import QualityLimits

if TYPE_CHECKING:
    from gateway.live.plausibility import Plausibility

__all__ = [
    "FAULT_CODES",
    "OTHERS_MOVED_C",
    "Quality",
    "QualityMonitor",
    "SensorCheck",
]

#: Transmitter status codes (0 = OK).
FAULT_CODES: Mapping[int, str] = {1: "open circuit", 2: "short circuit", 3: "out of range"}

#: Another sensor must move by more than this (°C) within the stuck window for a
#: constant value to count as stuck: "the machine is heating or cooling".
OTHERS_MOVED_C = 1.0


class Quality(StrEnum):
    GOOD = "good"
    BAD = "bad"


@dataclass(frozen=True)
class SensorCheck:
    """The verdict on one sensor for one cycle; ``reason`` is None when GOOD."""

    sensor: str
    quality: Quality
    reason: str | None


_time = itemgetter(0)


class _MovingRange:
    """max - min of a sensor's values since any time within the kept span, in O(log n).

    Two monotonic queues of (time_s, value): ``_highs`` keeps each value larger
    than every later one, ``_lows`` each value smaller than every later one.
    The largest value since t is then the first entry of ``_highs`` at or after
    t (a larger earlier entry would be larger than it, a later one is smaller),
    and likewise for the smallest. Times must increase; values must be finite.
    """

    __slots__ = ("_highs", "_lows")

    def __init__(self) -> None:
        self._highs: deque[tuple[float, float]] = deque()
        self._lows: deque[tuple[float, float]] = deque()

    def push(self, now_s: float, value: float, keep_from_s: float) -> None:
        """Add a value and forget those before ``keep_from_s``."""
        highs, lows = self._highs, self._lows
        while highs and highs[-1][1] <= value:
            highs.pop()
        highs.append((now_s, value))
        while lows and lows[-1][1] >= value:
            lows.pop()
        lows.append((now_s, value))
        while highs[0][0] < keep_from_s:
            highs.popleft()
        while lows[0][0] < keep_from_s:
            lows.popleft()

    def since(self, since_s: float) -> float:
        """max - min of the kept values at or after ``since_s`` (0 without any)."""
        highs, lows = self._highs, self._lows
        top = bisect_left(highs, since_s, key=_time)
        if top == len(highs):
            return 0.0
        return highs[top][1] - lows[bisect_left(lows, since_s, key=_time)][1]


@dataclass
class _SensorState:
    """What the monitor remembers about one sensor between cycles."""

    limits: QualityLimits
    last_check: SensorCheck
    last_good_C: float | None = None
    last_good_s: float | None = None
    good_streak: int = 0  # consecutive good checks since the last BAD one
    # The current run of values that stayed within stuck_band_C:
    run_start_s: float | None = None
    run_min_C: float = 0.0
    run_max_C: float = 0.0
    # run_start_s of the run found stuck: it stays stuck until the value moves.
    stuck_run_s: float | None = None
    # Plausible values (passed status, range and rate) kept for the "others moved" test.
    moves: _MovingRange = field(default_factory=_MovingRange)


class QualityMonitor:
    """Checks every sensor of one machine each cycle (see the module docstring)."""

    def __init__(
        self,
        sensors: Sequence[str],
        limits: QualityLimits | Mapping[str, QualityLimits],
        plausibility: Plausibility | None = None,
    ) -> None:
        names = list(sensors)
        if not names:
            raise ValueError("sensors must not be empty")
        if len(set(names)) != len(names):
            raise ValueError(f"sensors must be unique, got {names}")
        if isinstance(limits, QualityLimits):
            per_sensor = dict.fromkeys(names, limits)
        else:
            missing = [s for s in names if s not in limits]
            unknown = [s for s in limits if s not in names]
            if missing or unknown:
                raise ValueError(f"limits: missing for {missing}, unknown sensors {unknown}")
            per_sensor = {s: limits[s] for s in names}
        # Keep enough history to look back over the longest stuck window.
        self._history_s = max(lim.stuck_s for lim in per_sensor.values())
        self._states = {
            s: _SensorState(limits=lim, last_check=SensorCheck(s, Quality.BAD, "no value yet"))
            for s, lim in per_sensor.items()
        }
        # A verdict is immutable: each sensor's GOOD one is made once, not every cycle.
        self._good = {s: SensorCheck(s, Quality.GOOD, None) for s in per_sensor}
        self._start_s: float | None = None
        self._last_now_s: float | None = None
        self.plausibility = plausibility

    def last_good(self, sensor: str) -> float | None:
        """The last value of ``sensor`` that passed every check (°C), or None."""
        return self._states[sensor].last_good_C

    def check(
        self,
        now_s: float,
        readings: Mapping[str, tuple[float | None, int | None]],
        reference_C: Mapping[str, float] | None = None,
    ) -> dict[str, SensorCheck]:
        """Judge every sensor at machine time ``now_s``.

        ``readings`` maps sensor -> (value °C or None, transmitter status or None);
        a sensor missing from ``readings`` is treated as a missed read.
        ``reference_C``: the machine's cold reference; with it (and a plausibility
        check) the sensors are also judged against each other, by their rises.
        """
        self._advance(now_s, readings)
        # First the per-sensor checks that need no other sensor, then "stuck",
        # which needs every sensor's history up to this cycle.
        plausible: dict[str, float] = {}
        results: dict[str, SensorCheck] = {}
        for name, state in self._states.items():
            value, status = readings.get(name, (None, None))
            reason = self._plausibility(state, now_s, value, status)
            if reason is not None:
                state.run_start_s = None  # a bad sample breaks a constant run
                results[name] = self._verdict(state, name, reason)
            elif value is None:
                results[name] = self._missed_read(state, now_s)
            else:
                plausible[name] = value
                self._remember(state, now_s, value)

        for name, value in plausible.items():
            state = self._states[name]
            stuck = self._stuck_reason(name, state, now_s, value)
            if stuck is None:
                state.last_good_C, state.last_good_s = value, now_s
            results[name] = self._verdict(state, name, stuck)

        for name, result in results.items():
            self._states[name].last_check = result
        if self.plausibility is not None and reference_C is not None:
            self._hold_implausible(now_s, results, plausible, reference_C)
        return {name: results[name] for name in self._states}

    def _advance(
        self, now_s: float, readings: Mapping[str, tuple[float | None, int | None]]
    ) -> None:
        """Refuse readings of unknown sensors and a clock that does not move forward."""
        unknown = [s for s in readings if s not in self._states]
        if unknown:
            raise ValueError(f"readings for unknown sensors {unknown}")
        if self._last_now_s is not None and now_s <= self._last_now_s:
            raise ValueError(f"now_s must increase: {now_s} after {self._last_now_s}")
        if self._start_s is None:
            self._start_s = now_s
        self._last_now_s = now_s

    def _hold_implausible(
        self,
        now_s: float,
        results: dict[str, SensorCheck],
        plausible: Mapping[str, float],
        reference_C: Mapping[str, float],
    ) -> None:
        """Turn GOOD verdicts BAD where the sensors' rises, judged together, hold them."""
        assert self.plausibility is not None
        rises = {
            name: plausible[name] - reference_C[name]
            for name, result in results.items()
            if result.quality is Quality.GOOD and name in plausible and name in reference_C
        }
        held = self.plausibility.judge(now_s, rises)
        for name, reason in held.items():
            if results[name].quality is Quality.GOOD:
                results[name] = SensorCheck(name, Quality.BAD, reason)

    def mark_implausible(self, sensor: str, reason: str) -> SensorCheck:
        """The verdict for a sensor the loop's prediction rate bound has just held."""
        if sensor not in self._states:
            raise ValueError(f"unknown sensor {sensor}")
        return SensorCheck(sensor, Quality.BAD, reason)

    # -- individual checks -------------------------------------------------

    def _plausibility(
        self, state: _SensorState, now_s: float, value: float | None, status: int | None
    ) -> str | None:
        """Status, range and rate checks; None if the value is plausible (or absent)."""
        lim = state.limits
        if status not in (None, 0):
            meaning = FAULT_CODES.get(status)
            return f"transmitter fault code {status}" + (f" ({meaning})" if meaning else "")
        if value is None:
            return None
        if not math.isfinite(value):
            return f"not a finite value: {value}"
        if value > lim.max_C:
            return f"out of range: {value:.1f} °C > {lim.max_C:.1f} °C"
        if value < lim.min_C:
            return f"out of range: {value:.1f} °C < {lim.min_C:.1f} °C"
        if state.last_good_C is not None and state.last_good_s is not None:
            rate = abs(value - state.last_good_C) / (now_s - state.last_good_s)
            if rate > lim.max_rate_C_per_s:
                return f"rate {rate:.2f} °C/s > {lim.max_rate_C_per_s} °C/s"
        return None

    def _stuck_reason(
        self, name: str, state: _SensorState, now_s: float, value: float
    ) -> str | None:
        """BAD if the value has not moved for stuck_s while another sensor did.

        Once found stuck, a sensor stays stuck until its own value moves: the other
        sensors settling later does not make a frozen reading trustworthy again.
        """
        if state.run_start_s is None:
            return None
        held_s = now_s - state.run_start_s
        if state.stuck_run_s == state.run_start_s:
            return f"stuck at {value:.1f} °C for {held_s:.0f} s"
        if held_s < state.limits.stuck_s:
            return None
        for other, other_state in self._states.items():
            if other != name and _moved_since(other_state, state.run_start_s) > OTHERS_MOVED_C:
                state.stuck_run_s = state.run_start_s
                return f"stuck at {value:.1f} °C for {held_s:.0f} s"
        return None

    def _missed_read(self, state: _SensorState, now_s: float) -> SensorCheck:
        """No value this cycle: stale after stale_s, else repeat the previous verdict."""
        since_s = state.last_good_s if state.last_good_s is not None else self._start_s
        assert since_s is not None
        silent_s = now_s - since_s
        if silent_s > state.limits.stale_s:
            state.good_streak = 0
            return SensorCheck(
                state.last_check.sensor, Quality.BAD, f"stale: no value for {silent_s:.1f} s"
            )
        return state.last_check

    # -- bookkeeping -------------------------------------------------------

    def _verdict(self, state: _SensorState, name: str, reason: str | None) -> SensorCheck:
        """Apply the recovery hysteresis to one check's outcome."""
        if reason is not None:
            state.good_streak = 0
            return SensorCheck(name, Quality.BAD, reason)
        needed = state.limits.recover_cycles
        was_bad = state.last_check.quality is Quality.BAD
        if not was_bad:
            return self._good[name]
        state.good_streak += 1
        if state.good_streak >= needed:
            state.good_streak = 0
            return self._good[name]
        return SensorCheck(name, Quality.BAD, f"recovering ({state.good_streak}/{needed} good)")

    def _remember(self, state: _SensorState, now_s: float, value: float) -> None:
        """Record a plausible value: extend or restart the constant run, keep history."""
        band = state.limits.stuck_band_C
        if (
            state.run_start_s is not None
            and max(state.run_max_C, value) - min(state.run_min_C, value) <= band
        ):
            state.run_min_C = min(state.run_min_C, value)
            state.run_max_C = max(state.run_max_C, value)
        else:
            # Restarting at this sample (rather than searching back for the longest
            # run within the band) can only make a run look shorter: never a false stuck.
            state.run_start_s, state.run_min_C, state.run_max_C = now_s, value, value
        state.moves.push(now_s, value, now_s - self._history_s)


def _moved_since(state: _SensorState, since_s: float) -> float:
    """How far (max - min, °C) a sensor's plausible values moved since ``since_s``."""
    return state.moves.since(since_s)
