"""Which speed regime the spindle is in, and which stored model serves it.

Paper 002 (Miao et al. 2015) fits separate models on variable-speed ("spectrum")
runs and on constant-speed runs, and finds that each is best on its own regime
(:mod:`models.fit.ranking` ranks them). At run time the gateway must therefore decide,
from the recent spindle-speed history alone, which regime the machine is in:

- ``"idle"``: the spindle stood still for the whole window;
- ``"constant"`` (or ``"constant/<band>"`` when :attr:`RegimeRules.bands` split
  it): turning the whole window, with max - min speed within
  ``constant_tolerance_rpm``;
- ``"variable"``: anything else, including less than ``window_s`` of history.
  Unknown means variable because that is the robust choice: in paper 002's
  Table 4 the spectrum models hold up on constant-speed data (MN 2.92 µm) but the
  constant-speed models do not on spectrum data (MN 5.17 µm vs 1.75 µm at home).

:class:`RegimeSelector` adds hysteresis, because a model switch moves the
prediction and with it the compensation: a new regime must be seen continuously
for ``min_dwell_s`` before the selection changes, and ``"idle"`` never changes it
(a stopped spindle says nothing about the next programme, and the machine keeps
cooling along the path the current model knows).

Speeds are taken as magnitudes: M03 and M04 heat the bearings alike.

The selector runs every cycle of every machine, so its cost must not grow with
the window: it keeps running aggregates of the window (sliding max and min of
the speed magnitude, the count of stopped samples) and classifies from them in
O(1) amortized per update, with exactly the answers :func:`classify` gives on the
same history. :func:`classify` rebuilds three lists over the window: run every
cycle it cost 250 µs per update once the default 1800-s window was full at a 1 s
cycle, against 2-3 µs from the aggregates at any run time
(``benchmarks/cycle_cost_over_time.py``, CPU time).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from types import MappingProxyType

__all__ = [
    "CONSTANT",
    "IDLE",
    "STOPPED_BELOW_RPM",
    "VARIABLE",
    "RegimeRules",
    "RegimeSelector",
    "Selection",
    "SpeedBand",
    "classify",
]

VARIABLE = "variable"
CONSTANT = "constant"
IDLE = "idle"

#: A speed below this (r/min, magnitude) is a stopped spindle; actual-speed
#: feedback of a stopped spindle jitters by a few tenths, never by one r/min.
STOPPED_BELOW_RPM = 1.0


@dataclass(frozen=True)
class SpeedBand:
    """A named speed range [min_rpm, max_rpm) splitting the constant regime."""

    name: str
    min_rpm: float
    max_rpm: float

    def contains(self, speed_rpm: float) -> bool:
        return self.min_rpm <= speed_rpm < self.max_rpm


@dataclass(frozen=True)
class RegimeRules:
    """How to classify the speed history and which model serves each regime.

    Attributes:
        window_s: how much speed history the classification looks at.
        constant_tolerance_rpm: the largest max - min speed within the window
            (spindle turning throughout) that still counts as constant.
        min_dwell_s: how long a new regime must be seen continuously before the
            selection switches to it.
        bands: optional split of "constant" into "constant/<name>" by speed.
        models: regime label -> model id. A "constant/<band>" label without its
            own entry uses the "constant" entry, then ``fallback_model``.
        fallback_model: the model for a regime with no entry (None: no model).
    """

    window_s: float = 1800.0
    constant_tolerance_rpm: float = 150.0
    min_dwell_s: float = 600.0
    bands: tuple[SpeedBand, ...] = ()
    models: Mapping[str, str] = field(default_factory=dict)
    fallback_model: str | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window_s) and self.window_s > 0):
            raise ValueError(f"RegimeRules.window_s must be > 0, got {self.window_s}")
        if not (math.isfinite(self.constant_tolerance_rpm) and self.constant_tolerance_rpm >= 0):
            raise ValueError(
                "RegimeRules.constant_tolerance_rpm must be >= 0, "
                f"got {self.constant_tolerance_rpm}"
            )
        if not (math.isfinite(self.min_dwell_s) and self.min_dwell_s >= 0):
            raise ValueError(f"RegimeRules.min_dwell_s must be >= 0, got {self.min_dwell_s}")
        bands = tuple(self.bands)
        _check_bands(bands)
        names = [b.name for b in bands]
        known = {VARIABLE, CONSTANT} | {f"{CONSTANT}/{n}" for n in names}
        unknown = sorted(set(self.models) - known)
        if unknown:
            raise ValueError(
                f"RegimeRules.models: unknown regime labels {unknown}; known: {sorted(known)}"
            )
        object.__setattr__(self, "bands", bands)
        object.__setattr__(self, "models", MappingProxyType(dict(self.models)))

    def model_for(self, regime: str) -> str | None:
        """The model id serving ``regime``: its own, its parent's, or the fallback."""
        if regime in self.models:
            return self.models[regime]
        parent = regime.split("/", 1)[0]
        return self.models.get(parent, self.fallback_model)


def _check_bands(bands: tuple[SpeedBand, ...]) -> None:
    """Each band named and non-empty, names unique, no two bands overlapping."""
    for band in bands:
        if not band.name or "/" in band.name:
            raise ValueError(f"RegimeRules.bands: invalid band name {band.name!r}")
        if not band.min_rpm < band.max_rpm:
            raise ValueError(
                f"RegimeRules.bands: band {band.name!r} needs min_rpm < max_rpm, "
                f"got [{band.min_rpm}, {band.max_rpm})"
            )
    names = [b.name for b in bands]
    if len(set(names)) != len(names):
        raise ValueError(f"RegimeRules.bands: duplicate band names in {names}")
    ordered = sorted(bands, key=lambda b: b.min_rpm)
    for low, high in pairwise(ordered):
        if high.min_rpm < low.max_rpm:
            raise ValueError(
                f"RegimeRules.bands: {low.name!r} [{low.min_rpm}, {low.max_rpm}) overlaps "
                f"{high.name!r} [{high.min_rpm}, {high.max_rpm})"
            )


def classify(history: Sequence[tuple[float, float]], now_s: float, rules: RegimeRules) -> str:
    """The regime label of the speed ``history`` (time_s, speed_rpm) at ``now_s``.

    The speed is sample-and-hold: the last sample at or before the window start
    gives the speed at the window start. Without such a sample there is less than
    ``window_s`` of history and the answer is "variable" (see the module docstring).
    """
    start_s = now_s - rules.window_s
    before = [(t, v) for t, v in history if t <= start_s]
    if not before:
        return VARIABLE
    at_start_rpm = max(before, key=lambda sample: sample[0])[1]
    speeds = [abs(at_start_rpm)] + [abs(v) for t, v in history if start_s < t <= now_s]
    turning = [v >= STOPPED_BELOW_RPM for v in speeds]
    if not any(turning):
        return IDLE
    if not all(turning) or max(speeds) - min(speeds) > rules.constant_tolerance_rpm:
        return VARIABLE
    middle_rpm = (max(speeds) + min(speeds)) / 2
    for band in rules.bands:
        if band.contains(middle_rpm):
            return f"{CONSTANT}/{band.name}"
    return CONSTANT


@dataclass(frozen=True)
class Selection:
    """The regime and model to compensate with this cycle.

    ``switched`` is True when the caller must (re)load the model: on the first
    update and on the cycle the selected regime changes.
    """

    regime: str
    model_id: str | None
    switched: bool
    reason: str


class RegimeSelector:
    """Classifies each cycle's speed and switches the model with dwell hysteresis."""

    def __init__(self, rules: RegimeRules) -> None:
        self.rules = rules
        self._history: deque[tuple[float, float]] = deque()
        self._window = _WindowAggregates()
        self._selected: str | None = None
        self._candidate: str | None = None
        self._candidate_since_s = 0.0
        self._switches: list[tuple[float, str, str]] = []

    @property
    def switches(self) -> list[tuple[float, str, str]]:
        """Every change of the selected regime: (time_s, from, to)."""
        return list(self._switches)

    def update(self, now_s: float, speed_rpm: float) -> Selection:
        """Record this cycle's speed and return the selection for this cycle."""
        if not math.isfinite(speed_rpm):
            raise ValueError(f"speed_rpm must be finite, got {speed_rpm}")
        if self._history and now_s < self._history[-1][0]:
            raise ValueError(f"now_s went back: {now_s} after {self._history[-1][0]}")
        self._append(now_s, speed_rpm)
        seen = self._classify(now_s)

        if self._selected is None:
            self._selected = seen
            return self._selection(True, f"initial selection: {seen}")
        selected = self._selected
        if seen == IDLE:
            self._candidate = None
            return self._selection(False, f"idle: keeping {selected}")
        if seen == selected:
            self._candidate = None
            return self._selection(False, f"{seen}: unchanged")
        if seen != self._candidate:
            self._candidate, self._candidate_since_s = seen, now_s
        held_s = now_s - self._candidate_since_s
        if held_s < self.rules.min_dwell_s:
            return self._selection(
                False,
                f"{seen} for {held_s:.0f} s of {self.rules.min_dwell_s:.0f} s dwell: "
                f"keeping {selected}",
            )
        self._selected, self._candidate = seen, None
        self._switches.append((now_s, selected, seen))
        return self._selection(True, f"switched from {selected} to {seen} after {held_s:.0f} s")

    def _append(self, now_s: float, speed_rpm: float) -> None:
        """Append and drop what the window no longer needs.

        One sample at or before the window start is kept: it holds the speed at
        the window start, so the window counts as covered even when the cycle
        times never land exactly on now - window_s.
        """
        history = self._history
        history.append((now_s, speed_rpm))
        self._window.push(abs(speed_rpm))
        start_s = now_s - self.rules.window_s
        while len(history) >= 2 and history[1][0] <= start_s:
            self._window.pop(abs(history.popleft()[1]))

    def _classify(self, now_s: float) -> str:
        """``classify(self._history, now_s, self.rules)``, from the running aggregates.

        After :meth:`_append` only the first kept sample can lie at or before the
        window start (it holds the speed there) and every sample counts, so the
        speeds :func:`classify` looks at are the magnitudes of the kept samples.
        """
        if self._history[0][0] > now_s - self.rules.window_s:
            return VARIABLE
        window = self._window
        if window.stopped == window.count:
            return IDLE
        top_rpm, bottom_rpm = window.max_rpm(), window.min_rpm()
        if window.stopped or top_rpm - bottom_rpm > self.rules.constant_tolerance_rpm:
            return VARIABLE
        middle_rpm = (top_rpm + bottom_rpm) / 2
        for band in self.rules.bands:
            if band.contains(middle_rpm):
                return f"{CONSTANT}/{band.name}"
        return CONSTANT

    def _selection(self, switched: bool, reason: str) -> Selection:
        regime = self._selected
        assert regime is not None
        model_id = self.rules.model_for(regime)
        if model_id is None:
            reason += f"; no model for {regime}"
        elif regime not in self.rules.models:
            reason += f"; no own model for {regime}, using {model_id}"
        return Selection(regime, model_id, switched, reason)


class _WindowAggregates:
    """Max, min and stopped count of a FIFO window of speed magnitudes, O(1) amortized.

    The max and min are monotonic queues: each holds (sequence number, value) of
    the samples no later sample beats, so its front is the extreme of the window
    and leaves when that sample does. Every sample enters and leaves each queue
    at most once.
    """

    __slots__ = ("_highs", "_lows", "_popped", "_pushed", "count", "stopped")

    def __init__(self) -> None:
        self._highs: deque[tuple[int, float]] = deque()
        self._lows: deque[tuple[int, float]] = deque()
        self._pushed = 0  # sequence number of the next sample
        self._popped = 0  # sequence number of the oldest sample in the window
        self.count = 0
        self.stopped = 0  # samples below STOPPED_BELOW_RPM

    def push(self, speed_rpm: float) -> None:
        """Add the newest sample (a magnitude)."""
        sample = (self._pushed, speed_rpm)
        self._pushed += 1
        highs, lows = self._highs, self._lows
        while highs and highs[-1][1] <= speed_rpm:
            highs.pop()
        highs.append(sample)
        while lows and lows[-1][1] >= speed_rpm:
            lows.pop()
        lows.append(sample)
        self.count += 1
        self.stopped += speed_rpm < STOPPED_BELOW_RPM

    def pop(self, speed_rpm: float) -> None:
        """Drop the oldest sample, whose magnitude is ``speed_rpm``."""
        oldest = self._popped
        self._popped += 1
        if self._highs[0][0] == oldest:
            self._highs.popleft()
        if self._lows[0][0] == oldest:
            self._lows.popleft()
        self.count -= 1
        self.stopped -= speed_rpm < STOPPED_BELOW_RPM

    def max_rpm(self) -> float:
        return self._highs[0][1]

    def min_rpm(self) -> float:
        return self._lows[0][1]
