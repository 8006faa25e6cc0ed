"""First-order lags of every input at every searched time constant, so a new model starts warm.

An augmented model's lag terms depend on every sample since the cold reference
(:mod:`models.online.streaming`). A model in the bank from the start is stepped
every cycle, so it is warm whenever it is selected. A model promoted while the
gateway runs was not there: started from the present rises, its lags would
claim the machine had sat at today's temperatures forever.

The residual analysis picks its time constants from fixed grids
(:data:`models.data.lag_terms.LAG_TAUS_S` and its neighbours), so the loop keeps
the lag of every machine sensor's rise, of the speed terms and of the ambient
rise at each of those τ, with the very recursion a stream uses::

    x_k = a_k x_{k−1} + (1 − a_k) u_k,   a_k = exp(−Δt_k / τ),   x_0 = u_0

(across a logging gap, :func:`models.data.lag_terms.lag_coefficients`' exact
response to an input linear between samples; each input's last value is kept)

A model promoted later takes its lag states from here (:meth:`WarmLags.state_for`)
and predicts what it would have predicted had it been in the bank from the
first cycle. One difference: here each input steps whenever it is good, where a
stream holds all its lags in a cycle that lacks any of its inputs; the two agree
whenever every input was read, which is the normal case. A τ off the grids has
no warm state; that model's lags start from the present inputs (logged).

The cost is 19 inputs × 9 τ multiply-adds per cycle, and a few kB of state,
saved with the models' lag states (:mod:`gateway.live.bank.effect_lags`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from models.data.lag_terms import (
    AMBIENT_TAUS_S,
    HEAT_TAUS_S,
    LAG_TAUS_S,
    SPEED_SCALE_RPM,
    lag_step,
)
from models.online.streaming import (
    AMBIENT_INPUT,
    RECORDING_START_KEY,
    RUN_START_KEY,
    SPEED_COLUMNS,
    TIME_KEY,
    StreamingAugmented,
)

#: Every time constant the residual analysis searches (s), zero (no lag) left out.
TAUS_S = tuple(sorted({t for t in (*LAG_TAUS_S, *HEAT_TAUS_S, *AMBIENT_TAUS_S) if t > 0}))


class WarmLags:
    """The lag of each input at each τ of :data:`TAUS_S`, since the first cycle.

    Its clock (``start_s``, where ``drift`` counts from, and ``time_s``) starts
    with the first cycle that has a good input, as a stream's starts with its
    first complete sample.
    """

    def __init__(self, sensors: Iterable[str], ambient_sensor: str | None) -> None:
        self.sensors = tuple(sensors)
        self.ambient_sensor = ambient_sensor
        self.taus_s = np.array(TAUS_S)
        self.reset()

    def reset(self) -> None:
        """Forget every lag: the next cycle starts them from its inputs."""
        self.start_s: float | None = None  # first cycle stepped: where drift counts from
        self.time_s: float | None = None  # last cycle stepped
        self._values: dict[str, np.ndarray] = {}
        self._times: dict[str, float] = {}
        self._last: dict[str, float] = {}  # each input's last good value

    def step(self, time_s: float, rises_C: Mapping[str, float], speed_rpm: float | None) -> None:
        """Advance the lag of every input that is good this cycle."""
        if self.time_s is not None and time_s < self.time_s:
            self.reset()  # the clock went back: start again
        inputs: dict[str, float | None] = {s: rises_C.get(s) for s in self.sensors}
        if self.ambient_sensor is not None:
            inputs[AMBIENT_INPUT] = rises_C.get(self.ambient_sensor)
        if speed_rpm is not None and math.isfinite(speed_rpm):
            n = float(speed_rpm) / SPEED_SCALE_RPM
            inputs[SPEED_COLUMNS[0]], inputs[SPEED_COLUMNS[1]] = n, n * n
        good = {n: float(v) for n, v in inputs.items() if v is not None and math.isfinite(v)}
        if not good:
            return  # as a stream, whose clock starts with its first complete sample
        if self.start_s is None:
            self.start_s = float(time_s)
        self.time_s = float(time_s)
        # The inputs last stepped at the same time share one Δt: they step as one
        # (inputs × τ) array, the same multiply-adds as one row at a time, far fewer
        # numpy calls (all of them, normally: every input good every cycle).
        by_dt: dict[float, list[str]] = {}
        for name in good:
            if name in self._values:
                by_dt.setdefault(time_s - self._times[name], []).append(name)
            else:
                self._values[name] = np.full(self.taus_s.size, good[name])
        for dt_s, names in by_dt.items():
            previous = np.array([self._values[name] for name in names])
            inputs_now = np.array([[good[name]] for name in names])
            inputs_before = np.array([[self._last.get(name, good[name])] for name in names])
            stepped = lag_step(previous, inputs_before, inputs_now, dt_s, self.taus_s)
            for name, row in zip(names, stepped, strict=True):
                self._values[name] = row
        for name in good:
            self._times[name] = float(time_s)
            self._last[name] = good[name]

    def state_for(self, stream: StreamingAugmented) -> tuple[dict[str, float] | None, str]:
        """``stream``'s state as if it had been stepped since the first cycle, or (None, why)."""
        if self.time_s is None or self.start_s is None:
            return None, "no cycle has run yet"
        state = {
            TIME_KEY: self.time_s,
            RUN_START_KEY: self.start_s,
            RECORDING_START_KEY: self.start_s,
        }
        inputs: dict[str, float] = {}
        complete = True  # every input's last value known (not a state of an earlier release)
        for term in stream.terms:
            if not term.lagged:
                continue
            matches = np.flatnonzero(np.isclose(self.taus_s, term.tau_s, rtol=0, atol=1e-9))
            if matches.size == 0:
                return None, f"{term.effect} τ = {term.tau_s:g} s is not a searched time constant"
            for key, input_key, column in zip(
                term.state_keys(), term.input_keys(), term.columns, strict=True
            ):
                values = self._values.get(column)
                if values is None:
                    return None, f"no good value of {column} has been seen yet"
                state[key] = float(values[matches[0]])
                complete &= column in self._last
                inputs[input_key] = self._last.get(column, math.nan)
        if complete:
            state.update(inputs)
        return state, ""

    def export_state(self) -> dict[str, Any]:
        return {
            "taus_s": [float(t) for t in self.taus_s],
            "start_s": self.start_s,
            "time_s": self.time_s,
            "inputs": {
                name: {
                    "time_s": self._times[name],
                    "values": [float(v) for v in values],
                    "last": self._last.get(name),
                }
                for name, values in self._values.items()
            },
        }

    def import_state(self, state: Mapping[str, Any]) -> None:
        """Carry on from :meth:`export_state`; raises ValueError for a state that does not fit."""
        if [float(t) for t in state["taus_s"]] != [float(t) for t in self.taus_s]:
            raise ValueError("saved for other time constants")
        values = {str(k): np.asarray(v["values"], dtype=float) for k, v in state["inputs"].items()}
        times = {str(k): float(v["time_s"]) for k, v in state["inputs"].items()}
        if any(v.shape != self.taus_s.shape or not np.isfinite(v).all() for v in values.values()):
            raise ValueError("a saved lag is not a finite row of the right length")
        self.start_s = None if state["start_s"] is None else float(state["start_s"])
        self.time_s = None if state["time_s"] is None else float(state["time_s"])
        # "last" is absent from states saved by an earlier release: the next step holds
        saved = state["inputs"].items()
        last = {str(k): float(v["last"]) for k, v in saved if v.get("last") is not None}
        if not all(math.isfinite(v) for v in last.values()):
            raise ValueError("a saved input is not finite")
        self._values, self._times, self._last = values, times, last
