"""The earlier cycles the prediction rate bound compares with, kept as model rows.

The rate bound (rule 2 of :mod:`gateway.live.plausibility`) predicts, every cycle,
every earlier cycle of the last ``horizon_s`` again with this cycle's model and
speed: 120 cycles at a 1 s cycle. Rebuilding those rows from the kept rises and
predicting all of them each cycle made the rule's cost grow with the time a
machine had run, up to the horizon. Here the rows live in numpy arrays, built
once per cycle and sensor set, and each earlier cycle's prediction is kept
while the model object and the speed it was predicted at are unchanged; only
the cycles without a kept prediction (normally just the newest) are predicted.
With an MLR model the rule (check and accept) took 65 µs a cycle after 10 s of
run time and 75 µs from 120 s on, and takes 34 µs at any run time; with a speed
model at a speed that changes every cycle, 91-102 µs and 58-61 µs
(``benchmarks/cycle_cost_over_time.py``, CPU time).

A model that does not use the speed predicts the same at any speed, so for it
the speed is not part of what the kept predictions depend on. When the model,
its sensors or (for a speed model) the speed change, every row is predicted
again in one call, together with this cycle's row, exactly as the plain
computation does. Otherwise a row's prediction comes from an earlier call with
a different set of rows; numpy's BLAS kernels may then round the last bit
differently, as they already did when the plain computation predicted the same
earlier row in a window that had moved by a cycle.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

__all__ = ["Compared", "EarlierRows"]

_INITIAL_ROWS = 64


@dataclass(frozen=True)
class Compared:
    """This cycle's prediction and the earlier cycles it is compared with, in time order."""

    now_um: float
    then_um: np.ndarray
    spans_s: np.ndarray
    rows: np.ndarray  # (n, p) rises of the earlier cycles, the model's sensors in order
    index: np.ndarray  # where each earlier cycle is kept (for :meth:`EarlierRows.rises_of`)


class EarlierRows:
    """The trusted rises of the cycles within ``horizon_s``, with predictions kept."""

    def __init__(self, horizon_s: float) -> None:
        self.horizon_s = horizon_s
        self._rises: deque[Mapping[str, float]] = deque()  # to build rows for other sensors
        self._sensors: tuple[str, ...] | None = None
        self._model: object = None  # the model (and speed) the kept predictions are from
        self._speed: float | None = None
        self._start = self._end = 0
        # One row per kept cycle, from _start to _end (made by _allocate).
        self._times: np.ndarray
        self._rows: np.ndarray
        self._ok: np.ndarray  # every sensor trusted
        self._predicted: np.ndarray
        self._have: np.ndarray  # predicted kept
        self._allocate(_INITIAL_ROWS, 0)

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, time_s: float, rises_C: Mapping[str, float]) -> None:
        """Keep one cycle's trusted rises; forget the cycles more than the horizon before it."""
        if self._end == len(self._times):
            self._make_room()
        i = self._end
        self._end += 1
        self._rises.append(rises_C)
        self._times[i] = time_s
        self._have[i] = False
        if self._sensors is not None:
            self._fill(i, rises_C, self._sensors)
        times = self._times
        while self._start < self._end and time_s - times[self._start] > self.horizon_s:
            self._start += 1
            self._rises.popleft()

    def compare(
        self,
        now_s: float,
        sensors: tuple[str, ...],
        now_x: np.ndarray,
        model: object,
        speed_rpm: float | None,
        predict: Callable[[np.ndarray], np.ndarray],
    ) -> Compared | None:
        """This cycle's row and every earlier usable one in the horizon, predicted.

        ``predict`` maps (n, p) rows to n predictions of ``model`` at ``speed_rpm``
        (None for a model that does not read the speed). An earlier cycle is usable
        when all of ``sensors`` were trusted then. None: no usable earlier cycle.
        """
        self._use(sensors, model, speed_rpm)
        start, end = self._start, self._end
        times = self._times[start:end]
        usable = self._ok[start:end] & (now_s - times <= self.horizon_s)
        index = np.flatnonzero(usable) + start
        if index.size == 0:
            return None
        rows = self._rows[index]
        missing = ~self._have[index]
        if missing.all():
            predicted = predict(np.vstack([now_x, rows]))
            fresh = index
        else:
            fresh = index[missing]
            predicted = predict(np.vstack([now_x, self._rows[fresh]]))
        self._predicted[fresh] = predicted[1:]
        self._have[fresh] = True
        return Compared(
            now_um=predicted[0],
            then_um=self._predicted[index],
            spans_s=now_s - self._times[index],
            rows=rows,
            index=index,
        )

    def rises_of(self, index: int) -> Mapping[str, float]:
        """Every trusted rise of the earlier cycle kept at ``index`` (from :class:`Compared`)."""
        return self._rises[index - self._start]

    def clear(self) -> None:
        """Forget every earlier cycle: the next one kept is the new reference."""
        self._start = self._end
        self._rises.clear()

    def _use(self, sensors: tuple[str, ...], model: object, speed_rpm: float | None) -> None:
        """Rebuild the rows for new sensors; forget predictions of another model or speed."""
        start, end = self._start, self._end
        if sensors != self._sensors:
            self._sensors = sensors
            if self._rows.shape[1] != len(sensors):
                self._rows = np.empty((len(self._times), len(sensors)))
            for i, rises in zip(range(start, end), self._rises, strict=True):
                self._fill(i, rises, sensors)
            self._have[start:end] = False
        if model is not self._model or speed_rpm != self._speed:
            self._model, self._speed = model, speed_rpm
            self._have[start:end] = False

    def _fill(self, i: int, rises: Mapping[str, float], sensors: tuple[str, ...]) -> None:
        self._have[i] = False
        if all(s in rises for s in sensors):
            self._rows[i] = [rises[s] for s in sensors]
            self._ok[i] = True
        else:
            self._ok[i] = False

    def _make_room(self) -> None:
        """Move the kept cycles to the front, doubling the arrays when over half full."""
        kept = self._end - self._start
        size = len(self._times)
        self._allocate(size * 2 if kept > size // 2 else size, kept)

    def _allocate(self, size: int, kept: int) -> None:
        start, end = self._start, self._end
        columns = len(self._sensors) if self._sensors is not None else 0
        arrays = (
            np.empty(size),  # times
            np.empty((size, columns)),  # rows
            np.zeros(size, dtype=bool),  # ok: every sensor trusted
            np.empty(size),  # predicted
            np.zeros(size, dtype=bool),  # have: predicted kept
        )
        if kept:
            old = (self._times, self._rows, self._ok, self._predicted, self._have)
            for new, previous in zip(arrays, old, strict=True):
                new[:kept] = previous[start:end]
        self._times, self._rows, self._ok, self._predicted, self._have = arrays
        self._start, self._end = 0, kept
