"""Candidate effects a fitted model may lack, each as extra model terms.

Every candidate is a *family*: one physical effect with a small grid of
parameter values (a time constant, a sensor name, a time origin). The analysis
picks the value inside each validation fold, on that fold's training runs only.
Every term is zero in the error's reference state, the cold machine at rest
(:mod:`models.data.references`): temperatures as rises from their reference, the
speed from 0 r/min; the model's intercept carries the error's reference.

The families:

- ``thermal_lag``: first-order lags of the rises of the sensors the model
  uses, τ from 5 min to 8 h. A part no sensor touches (tool holder, spindle
  nose, a thick casting) follows the measured temperatures with a delay.
- ``speed_direct``: the speed n and n² (n in 1000 r/min): centrifugal and
  gyroscopic growth that appears with the speed, before any temperature moves.
- ``unsensed_heat``: first-order lags of n and n², τ from 10 min to 8 h:
  spindle heat reaching a part that no sensor measures, so only the heat input
  (the speed) tells how warm it is.
- ``ambient``: the rise of ``ambient_C``, as it is (τ = 0) or through a
  first-order lag up to 8 h (a big casting follows the hall slowly).
- ``drift``: time since the run (or the recording) started, in hours: probe,
  fixture or foundation creep.
- ``unused_sensor``: the rise of one measured column the model left out (a
  ``T`` column outside the model, or any other numeric column that is not a
  displacement — columns ending in ``_um`` are measured errors, which a
  gateway without a probe does not have).

Lag states start at the recording's first sample and carry across runs of one
continuous recording; each recording that starts cold starts its filter afresh:
a rise's lag at the rise's first value (≈ 0, the reference), a lag of the speed
at 0 (the unsensed part is cold, even when the spindle is already turning).

Between two samples a lag takes its input as the later sample (held over the
step), which is what a logger's rows mean at their own rate. Across a logging
gap (a step longer than :data:`GAP_S`) that would be wrong: a speed that went
from 8000 to 5000 r/min somewhere in a 25-minute gap would be charged as
5000 r/min for all of it. There the input is taken as the straight line between
the samples either side (first-order hold), the expected path of a change that
fell at an unknown moment in the gap, and the lag is the exact response to it.
:func:`lag_coefficients` gives both steps to the batch filter, and
:func:`lag_step`, its one-sample form, to every stream (:mod:`models.online.streaming`,
:mod:`models.estimators.lag_ridge`, ``gateway/live/bank/lag_state.py``), so they agree
across gaps too.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from models.data.dataset import AMBIENT_COLUMN, group_bounds
from models.data.features import Prepared
from models.data.references import first_rows

LAG_TAUS_S = (300.0, 600.0, 1200.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
HEAT_TAUS_S = (600.0, 1200.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
AMBIENT_TAUS_S = (0.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
SPEED_SCALE_RPM = 1000.0
DISPLACEMENT_SUFFIX = "_um"
UNIFORM_TOLERANCE = 1e-3  # relative spread of dt under which a recording counts as evenly sampled
#: A step between samples longer than this is a logging gap, s: across it a lag's
#: input is the straight line between the samples either side. Every logger and
#: poll rate here is 60 s or faster; a slower one is treated as gaps throughout,
#: which is the better rule at that rate anyway.
GAP_S = 120.0


@dataclass(frozen=True)
class Variant:
    """One parameter value of a family; ``build`` makes its (n, q) columns on demand
    (so a million-row file never holds every variant in memory at once)."""

    params: dict[str, Any]
    build: Callable[[], np.ndarray]
    signal_label: str


@dataclass(frozen=True)
class EffectFamily:
    effect: str
    label: str
    variants: tuple[Variant, ...] = field(default_factory=tuple)


def lag_coefficients(
    dt_s: np.ndarray | float, tau_s: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b_now, b_before) of one lag step: x_k = a x_{k−1} + b_now u_k + b_before u_{k−1}.

    a = exp(−Δt/τ). A step up to :data:`GAP_S` holds the new sample
    (b_now = 1 − a, b_before = 0). A longer step is a logging gap: the input is
    linear between u_{k−1} and u_k, whose exact response is
    b_before = (τ/Δt)(1 − a) − a, b_now = 1 − a − b_before. Arrays broadcast.
    """
    dt = np.asarray(dt_s, dtype=float)
    tau = np.asarray(tau_s, dtype=float)
    ratio = dt / tau
    a = np.exp(-ratio)
    one_minus_a = -np.expm1(-ratio)
    with np.errstate(divide="ignore", invalid="ignore"):
        linear = np.where(ratio > 0, one_minus_a / np.where(ratio > 0, ratio, 1.0) - a, 0.0)
    b_before = np.where(dt > GAP_S, linear, 0.0)
    return a, one_minus_a - b_before, b_before


def lag_step(
    state: np.ndarray,
    before: np.ndarray | None,
    now: np.ndarray,
    dt_s: float,
    tau_s: np.ndarray | float,
) -> np.ndarray:
    """One step of a stream's lag from the input ``before`` to ``now`` over ``dt_s``.

    ``before`` None (a state saved before the input was kept) holds ``now``. The
    common step, no gap, is the hold of :func:`lag_coefficients` written out: a
    stream takes it every cycle for every lag, and the general form costs ten times
    as much per call.
    """
    if dt_s <= GAP_S or before is None:
        a = np.exp(-dt_s / tau_s) if isinstance(tau_s, np.ndarray) else math.exp(-dt_s / tau_s)
        return a * state + (1.0 - a) * now
    a, b_now, b_before = lag_coefficients(dt_s, tau_s)
    return a * state + b_now * now + b_before * before


def first_order_lag(
    values: np.ndarray,
    time_s: np.ndarray,
    recording: np.ndarray,
    tau_s: float,
    start_cold: bool = False,
) -> np.ndarray:
    """x_k = a_k x_{k−1} + (1 − a_k) u_k, a_k = exp(−Δt_k / τ), per recording.

    Across a logging gap the step is :func:`lag_coefficients`'s first-order hold.
    The state starts at the recording's first value, so a rise that is 0 at the
    reference stays 0 until the input moves. With ``start_cold`` it starts at 0,
    the cold machine at rest: the lag of a heat input (the speed) in a recording
    that opens with the spindle already turning, whose unsensed part has not yet
    warmed. Evenly sampled recordings use
    ``scipy.signal.lfilter`` (fast on million-row files); others step sample by
    sample with their own Δt.
    """
    # Here, not at the top: scipy.signal (with scipy.stats) takes 2 s to import, and
    # loading a stored model (check-config, the start of run) never filters a recording.
    from scipy.signal import lfilter

    u = np.asarray(values, dtype=float)
    squeeze = u.ndim == 1
    u2 = u[:, None] if squeeze else u
    out = np.empty_like(u2)
    for s, e in zip(*group_bounds(recording), strict=True):
        segment = u2[s:e]
        first = np.zeros_like(segment[:1]) if start_cold else segment[:1]
        dt = np.diff(time_s[s:e])
        if dt.size == 0:
            out[s:e] = first
            continue
        out[s] = first
        if np.ptp(dt) <= UNIFORM_TOLERANCE * np.median(dt):
            a, b_now, b_before = (float(c) for c in lag_coefficients(np.median(dt), tau_s))
            # transposed direct form II: the state before u_1 is a·x_0 + b_before·u_0
            zi = a * first + b_before * segment[:1]
            out[s + 1 : e], _ = lfilter([b_now, b_before], [1, -a], segment[1:], axis=0, zi=zi)
        else:
            out[s + 1 : e] = _uneven_lag(first[0], segment, dt, tau_s)
    return out[:, 0] if squeeze else out


#: Largest decay (Δt/τ summed) inside one block of :func:`_uneven_lag`: e^20 ≈ 5·10⁸
#: keeps the block's rescaled sums far inside float range and their rounding at a few
#: ulps of the lag.
_BLOCK_DECAY = 20.0


def _uneven_lag(first: np.ndarray, u: np.ndarray, dt: np.ndarray, tau_s: float) -> np.ndarray:
    """Rows 1… of a lag over unevenly spaced samples, without a Python step per row.

    x_k = a_k x_{k−1} + c_k (c_k = b_now u_k + b_before u_{k−1}, :func:`lag_coefficients`)
    unrolls inside a block that starts at row s to
    x_i = e^{−(R_i − R_s)} (x_s + Σ_{s<j≤i} e^{R_j − R_s} c_j), R the running sum of
    Δt/τ: one cumulative sum per block. Blocks end before R has grown by
    :data:`_BLOCK_DECAY`, so the factors stay bounded; a gap much longer than τ starts a
    block of its own. A jittered million-row log steps in well under a second a lag,
    where a loop over rows took seconds.
    """
    a, b_now, b_before = lag_coefficients(dt, tau_s)
    decay = np.cumsum(dt / tau_s)
    block = np.floor(decay / _BLOCK_DECAY)
    starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
    ends = np.r_[starts[1:], decay.size]
    out = np.empty((dt.size, u.shape[1]))
    state = first.astype(float, copy=True)
    for s, e in zip(starts, ends, strict=True):
        # step k (row k + 1) takes c_k = b_now u_{k+1} + b_before u_k; made per block, so a
        # million-row file holds one (rows, columns) array besides its input
        c = b_now[s:e, None] * u[s + 1 : e + 1] + b_before[s:e, None] * u[s:e]
        state = a[s] * state + c[0]
        out[s] = state
        if e - s > 1:
            rel = decay[s + 1 : e] - decay[s]
            summed = np.cumsum(c[1:] * np.exp(rel)[:, None], axis=0)
            out[s + 1 : e] = np.exp(-rel)[:, None] * (state + summed)
            state = out[e - 1]
    return out


def hours_since_start(time_s: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Hours since the first sample of each row's group (run or recording)."""
    return (time_s - time_s[first_rows(group)]) / 3600.0


def candidate_families(prepared: Prepared, used_sensors: tuple[str, ...]) -> list[EffectFamily]:
    """Every family this data can support, given the sensors the model uses."""
    terms = _Terms(prepared)
    return [
        *terms.thermal_lag(used_sensors),
        *terms.speed(),
        *terms.ambient(),
        terms.drift(),
        *terms.unused_sensor(used_sensors),
    ]


class _Terms:
    """The candidate families' terms, made when a variant is built, not held: on a
    million-row file each (n,) column is megabytes, and only one family is tried at a time."""

    def __init__(self, prepared: Prepared) -> None:
        self.prepared = prepared
        self.data = prepared.data
        self.recording = prepared.plan.recording

    def speed_terms(self) -> np.ndarray:
        # From 0 r/min, the error's reference state (the cold machine at rest), as the
        # runtime takes them: a run that opens at speed keeps its growth at that speed.
        speed_krpm = self.data.speed_rpm / SPEED_SCALE_RPM
        return np.column_stack([speed_krpm, speed_krpm**2])

    def ambient_rise(self) -> np.ndarray:
        ambient_C = self.data.ambient_C
        assert ambient_C is not None, "an ambient term needs an ambient column"
        return self.prepared.plan.rises(ambient_C)

    def lagged(
        self, values: Callable[[], np.ndarray], tau: float, start_cold: bool = False
    ) -> Callable[[], np.ndarray]:
        time_s, recording = self.data.time_s, self.recording
        return lambda: (
            np.atleast_2d(first_order_lag(values(), time_s, recording, tau, start_cold).T).T
        )

    def thermal_lag(self, used_sensors: tuple[str, ...]) -> list[EffectFamily]:
        if not used_sensors:
            return []
        used_rises = self.prepared.inputs.columns(used_sensors)
        variants = tuple(
            Variant(
                {"tau_s": tau},
                self.lagged(lambda: used_rises, tau),
                f"lag (τ = {tau:g} s) of Δ{used_sensors[0]}, °C",
            )
            for tau in LAG_TAUS_S
        )
        what = f"first-order lags of the rises of {', '.join(used_sensors)}"
        return [EffectFamily("thermal_lag", what, variants)]

    def speed(self) -> list[EffectFamily]:
        if not np.ptp(self.data.speed_rpm) > 0:
            return []
        heat = tuple(
            Variant(
                {"tau_s": tau},
                self.lagged(self.speed_terms, tau, start_cold=True),
                f"lag (τ = {tau:g} s) of n, 1000 r/min",
            )
            for tau in HEAT_TAUS_S
        )
        return [
            EffectFamily(
                "speed_direct",
                "speed n and n² (n in 1000 r/min), from rest",
                (Variant({}, self.speed_terms, "speed n, 1000 r/min"),),
            ),
            EffectFamily(
                "unsensed_heat",
                "first-order lags of n and n² (heat reaching an unsensed part)",
                heat,
            ),
        ]

    def ambient(self) -> list[EffectFamily]:
        ambient = self.data.ambient_C
        if ambient is None or not np.ptp(ambient) > 0:
            return []
        variants = tuple(
            Variant(
                {"tau_s": tau},
                (lambda: self.ambient_rise()[:, None])
                if tau == 0
                else self.lagged(self.ambient_rise, tau),
                f"ambient_C rise (τ = {tau:g} s), °C",
            )
            for tau in AMBIENT_TAUS_S
        )
        what = "rise of ambient_C, direct (τ = 0) or through a first-order lag"
        return [EffectFamily("ambient", what, variants)]

    def drift(self) -> EffectFamily:
        time_s, data, recording = self.data.time_s, self.data, self.recording
        variants = [
            Variant(
                {"origin": "run"},
                lambda: hours_since_start(time_s, data.run_index)[:, None],
                "time in run, h",
            )
        ]
        if len(self.prepared.plan.recording_runs) < len(data.run_ids):
            variants.append(
                Variant(
                    {"origin": "recording"},
                    lambda: hours_since_start(time_s, recording)[:, None],
                    "time in recording, h",
                )
            )
        return EffectFamily("drift", "time since the start, h", tuple(variants))

    def unused_sensor(self, used_sensors: tuple[str, ...]) -> list[EffectFamily]:
        unused = unused_columns(self.prepared, used_sensors)
        if not unused:
            return []
        variants = tuple(
            Variant({"sensor": name}, _column_rise(self.prepared, name), f"Δ{name}")
            for name in unused
        )
        what = "rise of one measured column the model left out"
        return [EffectFamily("unused_sensor", what, variants)]


def unused_columns(prepared: Prepared, used_sensors: tuple[str, ...]) -> list[str]:
    """Measured columns a model could add: sensors it left out, other non-error signals."""
    data = prepared.data
    skip = {data.target, AMBIENT_COLUMN, *used_sensors}
    names = [name for name in data.column_order or data.numeric if name not in skip]

    def varies(name: str) -> bool:
        if name in data.released:  # readings let go; their rises are the model's inputs
            return data.released[name]
        return bool(np.ptp(data.numeric[name]) > 0)

    return [name for name in names if not name.endswith(DISPLACEMENT_SUFFIX) and varies(name)]


def _column_rise(prepared: Prepared, name: str) -> Callable[[], np.ndarray]:
    if name in prepared.data.released:
        # prepare() made exactly this rise from the readings that were let go
        return lambda: prepared.inputs.columns((name,))
    values = prepared.data.numeric[name]
    return lambda: prepared.plan.rises(values)[:, None]
