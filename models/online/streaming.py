"""An augmented model run one sample at a time, as the gateway's loop needs it.

:func:`models.analysis.augmented.predict` rebuilds every effect term over a whole data
file at once. A running machine has no file: each cycle brings one sample, and
the lag terms (``thermal_lag``, ``unsensed_heat``, ``ambient`` with τ > 0)
depend on every sample since the cold reference. :class:`StreamingAugmented`
therefore keeps one state per lagged term and advances it with each sample's
own Δt, using the same recursion as :func:`models.data.lag_terms.first_order_lag`::

    x_k = a_k x_{k−1} + (1 − a_k) u_k,   a_k = exp(−Δt_k / τ),   x_0 = u_0

(across a logging gap longer than :data:`models.data.lag_terms.GAP_S`, the exact
response to an input linear between u_{k−1} and u_k, so each lag also keeps
its last input)
(x_0 = 0 for the lags of the speed, ``unsensed_heat``: the part they stand
for is cold when the stream starts, even with the spindle already turning)

so that, fed the rows of one continuous recording in order, it gives the batch
predictions (within float rounding).

Inputs are rises above the cold reference, as for every model: sensor rises in
°C, the ambient rise in °C, and the speed as n − n_ref and n² − n_ref² with
n = speed_rpm / 1000 and n_ref the speed at the reference (default 0 r/min: the
cold reference is taken with the spindle stopped). ``drift`` counts hours from
a start time (default: the first sample stepped); a caller that knows where a
new run begins says so with :meth:`StreamingAugmented.start_run`, otherwise the
run and the recording start together.

A sample that lacks a needed input gives no prediction and leaves every state
where it was; the next complete sample's Δt then spans the gap. The state
(last time, start times, lag values) exports to a dict of plain floats so a
restarted gateway can carry on where it stopped.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from models.analysis.augmented import stored_base
from models.base import ModelInputs
from models.data.lag_terms import SPEED_SCALE_RPM, lag_step
from models.store import StoreError

SECONDS_PER_HOUR = 3600.0
SPEED_COLUMNS = ("n_krpm", "n2_krpm2")  # the speed terms: n and n², n in 1000 r/min
AMBIENT_INPUT = "ambient_C"
TIME_KEY = "time_s"
RUN_START_KEY = "run_start_s"
RECORDING_START_KEY = "recording_start_s"
BASE_PREFIX = "base."  # state keys of a base model's own lags


@dataclass(frozen=True)
class EffectTerm:
    """One stored effect: where its input comes from and whether it is lagged."""

    index: int  # position in the document's ``effects``
    effect: str
    columns: tuple[str, ...]  # one name per model term (a sensor, a speed power, …)
    tau_s: float  # > 0: first-order lag with this time constant; 0: the input as it is
    origin: str = ""  # drift only: "run" or "recording"

    @property
    def lagged(self) -> bool:
        return self.tau_s > 0

    def state_keys(self) -> list[str]:
        return [f"{self.effect}#{self.index}.{column}" for column in self.columns]

    def input_keys(self) -> list[str]:
        """Keys of the last input each lag stepped with (the start of a gap's line)."""
        return [f"{key}.input" for key in self.state_keys()]


class StreamingAugmented:
    """A stored augmented model (:mod:`models.analysis.augmented`) stepped sample by sample."""

    def __init__(
        self,
        document: Mapping[str, Any],
        *,
        speed_ref_rpm: float = 0.0,
        start_s: float | None = None,
    ) -> None:
        self.model_id = str(document["model_id"])
        self.base = stored_base(document)
        # A base whose own terms remember the history (lag-ridge) steps its own lags.
        make_stream = getattr(self.base, "stream", None)
        self.base_stream = make_stream() if callable(make_stream) else None
        self.base_sensors = tuple(self.base.sensors_used_)
        self.effect_sensors = tuple(document.get("effect_sensors", self.base_sensors))
        self.terms = [
            self._term(i, effect["effect"], effect.get("params", {}))
            for i, effect in enumerate(document["effects"])
        ]
        for term, effect in zip(self.terms, document["effects"], strict=True):
            stored = effect.get("terms", len(term.columns))
            if stored != len(term.columns):
                raise StoreError(
                    f"{self.model_id}: effect {term.effect} has {stored} terms stored, "
                    f"{len(term.columns)} expected"
                )
        self.coefficients = np.asarray(document["coefficients"]["all_um_per_unit"], dtype=float)
        base_terms = (
            1
            if self.base_stream is not None
            else self._base_row({s: 0.0 for s in self.base_sensors}, 0.0).size
        )
        expected = 1 + base_terms + sum(len(t.columns) for t in self.terms)
        if self.coefficients.size != expected:
            raise StoreError(
                f"{self.model_id}: {self.coefficients.size} coefficients stored "
                f"for {expected} terms"
            )
        self.speed_ref_krpm = speed_ref_rpm / SPEED_SCALE_RPM
        self.uses_speed = self.base.uses_speed or any(
            t.effect in ("speed_direct", "unsensed_heat") for t in self.terms
        )
        self.uses_ambient = any(t.effect == "ambient" for t in self.terms)
        needed = list(self.base_sensors)
        for term in self.terms:
            if term.effect in ("thermal_lag", "unused_sensor"):
                needed += term.columns
        self.sensors = tuple(dict.fromkeys(needed))
        self._start_s = start_s
        self.reset()

    def _term(self, index: int, effect: str, params: Mapping[str, Any]) -> EffectTerm:
        if effect == "thermal_lag":
            if not self.effect_sensors:
                raise StoreError(f"{self.model_id}: thermal_lag without effect_sensors")
            return EffectTerm(index, effect, self.effect_sensors, self._tau_s(params))
        if effect == "speed_direct":
            return EffectTerm(index, effect, SPEED_COLUMNS, 0.0)
        if effect == "unsensed_heat":
            return EffectTerm(index, effect, SPEED_COLUMNS, self._tau_s(params))
        if effect == "ambient":
            return EffectTerm(index, effect, (AMBIENT_INPUT,), self._tau_s(params))
        if effect == "drift":
            origin = str(params["origin"])
            if origin not in ("run", "recording"):
                raise StoreError(f"{self.model_id}: drift origin {origin!r} is unknown")
            return EffectTerm(index, effect, (f"{origin}_hours",), 0.0, origin)
        if effect == "unused_sensor":
            return EffectTerm(index, effect, (str(params["sensor"]),), 0.0)
        raise StoreError(f"{self.model_id}: unknown effect {effect!r}")

    def _tau_s(self, params: Mapping[str, Any]) -> float:
        tau_s = float(params["tau_s"])
        if not (math.isfinite(tau_s) and tau_s >= 0):
            raise StoreError(f"{self.model_id}: time constant {tau_s} s is not >= 0")
        return tau_s

    # --- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every state: the next sample starts the lags and, unless given, the clock."""
        self._time_s: float | None = None
        self._recording_start_s = self._start_s
        self._run_start_s = self._start_s
        self._lags: dict[int, np.ndarray] = {}
        self._last_inputs: dict[int, np.ndarray] = {}  # each lag's last input
        if self.base_stream is not None:
            self.base_stream.reset()

    @property
    def time_s(self) -> float | None:
        """Time of the last sample stepped (None before the first)."""
        return self._time_s

    def start_run(self, time_s: float) -> None:
        """A new run begins at ``time_s``: ``drift`` with origin "run" counts from here."""
        self._run_start_s = float(time_s)

    def export_state(self) -> dict[str, float]:
        """Everything the next step depends on, as plain floats ({} before the first step)."""
        if self._time_s is None:
            return {}
        assert self._run_start_s is not None and self._recording_start_s is not None
        state = {
            TIME_KEY: self._time_s,
            RUN_START_KEY: self._run_start_s,
            RECORDING_START_KEY: self._recording_start_s,
        }
        for term in self.terms:
            if term.lagged:
                values = self._lags[term.index]
                state.update(zip(term.state_keys(), map(float, values), strict=True))
        lagged = [term for term in self.terms if term.lagged]
        if all(term.index in self._last_inputs for term in lagged):  # not from an old state
            for term in lagged:
                last = self._last_inputs[term.index]
                state.update(zip(term.input_keys(), map(float, last), strict=True))
        if self.base_stream is not None:
            state.update(
                {f"{BASE_PREFIX}{k}": v for k, v in self.base_stream.export_state().items()}
            )
        return state

    def import_state(self, state: Mapping[str, float]) -> None:
        """Carry on from :meth:`export_state` of the same model; {} starts afresh.

        A state saved before the lags kept their last input (no ``….input`` keys)
        still loads: its next step holds the new sample, gap or not.
        """
        if not state:
            self.reset()
            return
        lag_keys = [key for term in self.terms if term.lagged for key in term.state_keys()]
        input_keys = [key for term in self.terms if term.lagged for key in term.input_keys()]
        base_state = {
            k[len(BASE_PREFIX) :]: v for k, v in state.items() if k.startswith(BASE_PREFIX)
        }
        state = {k: v for k, v in state.items() if not k.startswith(BASE_PREFIX)}
        if self.base_stream is None and base_state:
            raise ValueError(f"{self.model_id}: state holds base lags this model does not have")
        expected = {TIME_KEY, RUN_START_KEY, RECORDING_START_KEY, *lag_keys, *input_keys}
        if set(state) != expected and set(state) != expected - set(input_keys):
            missing, extra = sorted(expected - set(state)), sorted(set(state) - expected)
            raise ValueError(
                f"{self.model_id}: state does not fit this model (missing {missing}, "
                f"unknown {extra})"
            )
        values = {key: float(value) for key, value in state.items()}
        if not all(math.isfinite(v) for v in values.values()):
            raise ValueError(f"{self.model_id}: state holds a value that is not finite")
        if self.base_stream is not None:
            self.base_stream.import_state(base_state)  # checks its own keys and values
        self._time_s = values[TIME_KEY]
        self._run_start_s = values[RUN_START_KEY]
        self._recording_start_s = values[RECORDING_START_KEY]
        self._lags = {
            term.index: np.array([values[key] for key in term.state_keys()])
            for term in self.terms
            if term.lagged
        }
        self._last_inputs = {
            term.index: np.array([values[key] for key in term.input_keys()])
            for term in self.terms
            if term.lagged and term.input_keys()[0] in values
        }

    # --- one sample ----------------------------------------------------------------------
    def step(
        self,
        time_s: float,
        rises_C: Mapping[str, float],
        speed_rpm: float | None,
        ambient_rise_C: float | None = None,
    ) -> float | None:
        """Advance every state to ``time_s`` and return the predicted error rise, µm.

        None (and no state advanced) when a needed sensor rise, the speed or the
        ambient rise is missing or not finite. Time must not go back.
        """
        if not self._complete(rises_C, speed_rpm, ambient_rise_C):
            return None
        if self._time_s is not None and time_s < self._time_s:
            raise ValueError(f"{self.model_id}: time went back: {time_s} s after {self._time_s} s")
        if self._recording_start_s is None:
            self._recording_start_s = float(time_s)
        if self._run_start_s is None:
            self._run_start_s = float(time_s)
        dt_s = 0.0 if self._time_s is None else time_s - self._time_s
        speed = 0.0 if speed_rpm is None else float(speed_rpm)
        if self.base_stream is not None:
            base = self.base_stream.step(time_s, rises_C, speed)
            assert base is not None  # _complete checked its inputs
            row = [np.ones(1), np.array([base])]
        else:
            row = [np.ones(1), self._base_row(rises_C, speed)]
        for term in self.terms:
            values = self._inputs(term, time_s, rises_C, speed, ambient_rise_C)
            if term.lagged:
                previous = self._lags.get(term.index)
                now = values
                if previous is not None:
                    before = self._last_inputs.get(term.index)
                    values = lag_step(previous, before, now, dt_s, term.tau_s)
                elif term.effect == "unsensed_heat":
                    values = np.zeros_like(values)  # the unsensed part starts cold
                self._lags[term.index] = values
                self._last_inputs[term.index] = now
            row.append(values)
        self._time_s = float(time_s)
        return float(self.coefficients @ np.concatenate(row))

    def _complete(
        self,
        rises_C: Mapping[str, float],
        speed_rpm: float | None,
        ambient_rise_C: float | None,
    ) -> bool:
        if any(_missing(rises_C.get(s)) for s in self.sensors):
            return False
        if self.uses_speed and _missing(speed_rpm):
            return False
        return not (self.uses_ambient and _missing(ambient_rise_C))

    def _base_row(self, rises_C: Mapping[str, float], speed_rpm: float) -> np.ndarray:
        inputs = ModelInputs(
            rise_C=np.array([[rises_C[s] for s in self.base_sensors]], dtype=float),
            sensors=self.base_sensors,
            speed_rpm=np.array([speed_rpm]),
        )
        return np.asarray(self.base.design_matrix(inputs), dtype=float)[0]

    def _inputs(
        self,
        term: EffectTerm,
        time_s: float,
        rises_C: Mapping[str, float],
        speed_rpm: float,
        ambient_rise_C: float | None,
    ) -> np.ndarray:
        """The term's input at this sample (before any lag), one value per column."""
        if term.effect in ("speed_direct", "unsensed_heat"):
            n = speed_rpm / SPEED_SCALE_RPM
            n_ref = self.speed_ref_krpm
            return np.array([n - n_ref, n * n - n_ref * n_ref])
        if term.effect == "ambient":
            assert ambient_rise_C is not None
            return np.array([float(ambient_rise_C)])
        if term.effect == "drift":
            start = self._run_start_s if term.origin == "run" else self._recording_start_s
            assert start is not None
            return np.array([(time_s - start) / SECONDS_PER_HOUR])
        return np.array([float(rises_C[name]) for name in term.columns])


def _missing(value: float | None) -> bool:
    return value is None or not math.isfinite(value)
