"""Candidate effects a fitted model may lack, each as extra model terms.

Every candidate is a *family*: one physical effect with a small grid of
parameter values (a time constant, a sensor name, a time origin). The analysis
picks the value inside each validation fold, on that fold's training runs only.
Every term is zero in the error's reference state, the cold machine at rest
(:mod:`models.references`): temperatures as rises from their reference, the
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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.signal import lfilter

from models.dataset import AMBIENT_COLUMN, group_bounds
from models.features import Prepared
from models.references import first_rows

LAG_TAUS_S = (300.0, 600.0, 1200.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
HEAT_TAUS_S = (600.0, 1200.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
AMBIENT_TAUS_S = (0.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
SPEED_SCALE_RPM = 1000.0
DISPLACEMENT_SUFFIX = "_um"
UNIFORM_TOLERANCE = 1e-3  # relative spread of dt under which a recording counts as evenly sampled


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


def first_order_lag(
    values: np.ndarray,
    time_s: np.ndarray,
    recording: np.ndarray,
    tau_s: float,
    start_cold: bool = False,
) -> np.ndarray:
    """x_k = a_k x_{k−1} + (1 − a_k) u_k, a_k = exp(−Δt_k / τ), per recording.

    The state starts at the recording's first value, so a rise that is 0 at the
    reference stays 0 until the input moves. With ``start_cold`` it starts at 0,
    the cold machine at rest: the lag of a heat input (the speed) in a recording
    that opens with the spindle already turning, whose unsensed part has not yet
    warmed. Evenly sampled recordings use
    ``scipy.signal.lfilter`` (fast on million-row files); others step sample by
    sample with their own Δt.
    """
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
        if np.ptp(dt) <= UNIFORM_TOLERANCE * np.median(dt):
            a = float(np.exp(-np.median(dt) / tau_s))
            out[s] = first
            out[s + 1 : e], _ = lfilter([1 - a], [1, -a], segment[1:], axis=0, zi=a * first)
        else:
            a_k = np.exp(-dt / tau_s)
            state = first[0].copy()
            out[s] = state
            for k in range(1, e - s):
                state = a_k[k - 1] * state + (1 - a_k[k - 1]) * segment[k]
                out[s + k] = state
    return out[:, 0] if squeeze else out


def hours_since_start(time_s: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Hours since the first sample of each row's group (run or recording)."""
    return (time_s - time_s[first_rows(group)]) / 3600.0


def candidate_families(prepared: Prepared, used_sensors: tuple[str, ...]) -> list[EffectFamily]:
    """Every family this data can support, given the sensors the model uses."""
    data = prepared.data
    recording = prepared.plan.recording
    time_s = data.time_s
    used_rises = prepared.inputs.columns(used_sensors) if used_sensors else None

    # Terms are made when a variant is built, not held: on a million-row file each
    # (n,) column is megabytes, and only one family is tried at a time.
    def speed_terms() -> np.ndarray:
        # From 0 r/min, the error's reference state (the cold machine at rest), as the
        # runtime takes them: a run that opens at speed keeps its growth at that speed.
        speed_krpm = data.speed_rpm / SPEED_SCALE_RPM
        return np.column_stack([speed_krpm, speed_krpm**2])

    def ambient_rise() -> np.ndarray:
        return prepared.plan.rises(data.ambient_C)

    def lagged(
        values: Callable[[], np.ndarray], tau: float, start_cold: bool = False
    ) -> Callable[[], np.ndarray]:
        return lambda: (
            np.atleast_2d(first_order_lag(values(), time_s, recording, tau, start_cold).T).T
        )

    families: list[EffectFamily] = []
    if used_rises is not None:
        families.append(
            EffectFamily(
                "thermal_lag",
                f"first-order lags of the rises of {', '.join(used_sensors)}",
                tuple(
                    Variant(
                        {"tau_s": tau},
                        lagged(lambda: used_rises, tau),
                        f"lag (τ = {tau:g} s) of Δ{used_sensors[0]}, °C",
                    )
                    for tau in LAG_TAUS_S
                ),
            )
        )
    if np.ptp(data.speed_rpm) > 0:
        families.append(
            EffectFamily(
                "speed_direct",
                "speed n and n² (n in 1000 r/min), from rest",
                (Variant({}, speed_terms, "speed n, 1000 r/min"),),
            )
        )
        families.append(
            EffectFamily(
                "unsensed_heat",
                "first-order lags of n and n² (heat reaching an unsensed part)",
                tuple(
                    Variant(
                        {"tau_s": tau},
                        lagged(speed_terms, tau, start_cold=True),
                        f"lag (τ = {tau:g} s) of n, 1000 r/min",
                    )
                    for tau in HEAT_TAUS_S
                ),
            )
        )
    ambient = data.ambient_C
    if ambient is not None and np.ptp(ambient) > 0:
        families.append(
            EffectFamily(
                "ambient",
                "rise of ambient_C, direct (τ = 0) or through a first-order lag",
                tuple(
                    Variant(
                        {"tau_s": tau},
                        (lambda: ambient_rise()[:, None])
                        if tau == 0
                        else lagged(ambient_rise, tau),
                        f"ambient_C rise (τ = {tau:g} s), °C",
                    )
                    for tau in AMBIENT_TAUS_S
                ),
            )
        )

    def run_hours() -> np.ndarray:
        return hours_since_start(time_s, data.run_index)[:, None]

    def recording_hours() -> np.ndarray:
        return hours_since_start(time_s, recording)[:, None]

    drift_variants = [Variant({"origin": "run"}, run_hours, "time in run, h")]
    if len(prepared.plan.recording_runs) < len(data.run_ids):
        drift_variants.append(
            Variant({"origin": "recording"}, recording_hours, "time in recording, h")
        )
    families.append(EffectFamily("drift", "time since the start, h", tuple(drift_variants)))
    unused = unused_columns(prepared, used_sensors)
    if unused:
        families.append(
            EffectFamily(
                "unused_sensor",
                "rise of one measured column the model left out",
                tuple(
                    Variant(
                        {"sensor": name},
                        _column_rise(prepared, name),
                        f"Δ{name}",
                    )
                    for name in unused
                ),
            )
        )
    return families


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
