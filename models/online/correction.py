"""Online correction of a fitted model from probe measurements: a small Kalman filter.

A touch probe on an artefact measures, every so often, the real thermal error at
the tool. The fitted model's *residual* at that instant (measured − predicted,
µm; see contracts §7 for how the runtime gets it from the probe macro) is the
part of the error the model misses: a slow offset from a new fixture, preload,
coolant, or an effect the model lacks. This class estimates that residual with
a Kalman filter and adds the estimate to the model's prediction between probes.

State models (``kind``):

- ``bias``: one state, the additive bias b (µm). First-order mean-reverting
  (Ornstein–Uhlenbeck) with time constant ``reversion_tau_s``, or a random walk
  when that is ``None``::

      b(t+Δ) = a b(t) + w,  a = exp(−Δ/τ),  Var w = q τ/2 (1 − a²)   (q Δ when τ = ∞)

- ``bias-rate``: bias and its rate ḃ (µm/h), a constant-velocity model with
  white rate noise (the rate random-walks)::

      x = [b, ḃ],  F = [[1, Δ], [0, 1]],  Q = q_rate [[Δ³/3, Δ²/2], [Δ²/2, Δ]] + diag(q Δ, 0)

  (Δ in hours). It follows a residual that keeps drifting between probes.

- ``bias-gain``: bias and a gain error g (µm per µm of the model's prediction ŷ),
  both random walks::

      x = [b, g],  F = I,  Q = diag(q Δ, q_gain Δ),  residual = b + g ŷ(t)

  A model whose growth is too large or too small by a fraction for this machine
  state leaves a residual proportional to its own prediction; a bias would have
  to follow every change of ŷ from probe to probe. The gain carries it between
  probes, so this kind needs the model's prediction: at a probe (H = [1, ŷ]) and
  wherever the correction is evaluated.

``q`` is ``process_um2_per_h`` (variance the bias gains per hour), ``q_rate`` is
``rate_process_um2_per_h3``, ``q_gain`` is ``gain_process_per_h`` (variance the
dimensionless gain gains per hour), and the probe's own noise is ``probe_noise_um``
(σ, µm). Every probe is one scalar measurement z of the residual, H = [1, 0] (or
[1, ŷ] for ``bias-gain``).

Safety, by construction:

- **innovation test**: a probe value more than ``outlier_sigma`` (k) standard
  deviations from the filter's prediction, |z − H x⁻| > k √(H P⁻ Hᵀ + R), is
  refused (counted in ``refused``; the caller logs it) and leaves the state as
  it was, so a chip under the probe does not move the machine. After
  ``reset_after_refusals`` refusals in a row the machine has really changed
  (a chip is not under the probe three times running): the filter forgets its
  state (P back to the prior) and takes that probe;
- **bound**: the correction applied is clipped to ±``bound_um``;
- **silence**: once no probe has been accepted for ``decay_after_s``, the
  applied correction decays toward zero as exp(−(t − t_last − decay_after_s) /
  ``decay_tau_s``): an old correction is no longer trusted.

The filter is pure numpy and deterministic. :meth:`correction_at` evaluates the
correction at any times after the last update without changing the state, so
the runtime (one value per cycle) and ``replay`` (a whole run at once) share the
same arithmetic. Parameters and state export to plain JSON dicts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Literal

import numpy as np

SECONDS_PER_HOUR = 3600.0
KINDS = ("bias", "bias-rate", "bias-gain")
# What a fit chooses and a model stores; the rest (bound, decay) are the machine's safety limits.
NOISE_FIELDS = (
    "kind",
    "process_um2_per_h",
    "rate_process_um2_per_h3",
    "gain_process_per_h",
    "gain_prior",
    "reversion_tau_s",
    "probe_noise_um",
    "outlier_sigma",
)
Kind = Literal["bias", "bias-rate", "bias-gain"]


@dataclass(frozen=True)
class CorrectionParams:
    """Noise model and safety limits of the online correction (units in the names)."""

    kind: Kind = "bias"
    process_um2_per_h: float = 1.0
    rate_process_um2_per_h3: float = 0.0
    gain_process_per_h: float = 0.0
    gain_prior: float = 0.5  # σ of the gain error before any probe (µm per µm)
    reversion_tau_s: float | None = None
    probe_noise_um: float = 0.3
    prior_um: float = 5.0
    outlier_sigma: float = 4.0
    bound_um: float = 20.0
    decay_after_s: float = 4 * SECONDS_PER_HOUR
    decay_tau_s: float = SECONDS_PER_HOUR
    reset_after_refusals: int = 2

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"online correction kind {self.kind!r}: expected one of {KINDS}")
        positive = (
            "probe_noise_um",
            "prior_um",
            "gain_prior",
            "outlier_sigma",
            "bound_um",
            "decay_tau_s",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"online correction {name} = {value}: expected a number > 0")
        nonnegative = (
            "process_um2_per_h",
            "rate_process_um2_per_h3",
            "gain_process_per_h",
            "decay_after_s",
        )
        for name in nonnegative:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"online correction {name} = {value}: expected a number >= 0")
        tau = self.reversion_tau_s
        if tau is not None and not (math.isfinite(tau) and tau > 0):
            raise ValueError(f"online correction reversion_tau_s = {tau}: expected > 0 or null")
        if self.reset_after_refusals < 1:
            raise ValueError("online correction reset_after_refusals: expected >= 1")

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> CorrectionParams:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"online correction: unknown parameter(s) {unknown}")
        return cls(**dict(values))

    def with_limits(self, **limits: Any) -> CorrectionParams:
        """The same parameters with the ones named replaced."""
        return replace(self, **limits)

    def with_noise_of(self, stored: Mapping[str, Any]) -> CorrectionParams:
        """These safety limits with the noise model (``NOISE_FIELDS``) a model stored."""
        return replace(self, **{k: stored[k] for k in NOISE_FIELDS if k in stored})


@dataclass(frozen=True)
class ProbeOutcome:
    """What one probe did to the filter."""

    time_s: float
    residual_um: float
    predicted_um: float  # the filter's prediction of the residual before the probe (µm)
    innovation_sigma_um: float  # √S
    accepted: bool
    reason: str


class OnlineCorrection:
    """Kalman filter on a model's residual; see the module docstring."""

    def __init__(self, params: CorrectionParams | None = None) -> None:
        self.params = params or CorrectionParams()
        self.reset()

    # --- state ---------------------------------------------------------------------------
    @property
    def size(self) -> int:
        return 1 if self.params.kind == "bias" else 2

    def reset(self) -> None:
        """Forget every probe: no correction until the next one."""
        n = self.size
        self.x = np.zeros(n)
        self.P = self._prior()
        self.time_s: float | None = None  # time of the state (last probe seen)
        self.last_accepted_s: float | None = None
        self.accepted = 0
        self.refused = 0
        self.refused_in_row = 0

    @property
    def needs_prediction(self) -> bool:
        """True when the correction depends on the model's prediction (``bias-gain``)."""
        return self.params.kind == "bias-gain"

    def _prior(self) -> np.ndarray:
        prior = np.zeros((self.size, self.size))
        prior[0, 0] = self.params.prior_um**2
        if self.params.kind == "bias-rate":
            prior[1, 1] = self.params.prior_um**2  # (µm/h)²: a rate as large as the prior bias
        elif self.params.kind == "bias-gain":
            prior[1, 1] = self.params.gain_prior**2
        return prior

    def _h(self, predicted_um: float | None) -> np.ndarray:
        """The measurement row: the residual the state predicts is H x."""
        if self.params.kind == "bias-gain":
            assert predicted_um is not None
            return np.array([1.0, predicted_um])
        return np.array([1.0] + [0.0] * (self.size - 1))

    def export_state(self) -> dict[str, Any]:
        return {
            "x": [float(v) for v in self.x],
            "P": [[float(v) for v in row] for row in self.P],
            "time_s": self.time_s,
            "last_accepted_s": self.last_accepted_s,
            "accepted": self.accepted,
            "refused": self.refused,
            "refused_in_row": self.refused_in_row,
        }

    def import_state(self, state: Mapping[str, Any]) -> None:
        x = np.asarray(state["x"], dtype=float)
        P = np.asarray(state["P"], dtype=float)
        if x.shape != (self.size,) or P.shape != (self.size, self.size):
            raise ValueError(f"online correction state does not fit kind {self.params.kind!r}")
        self.x, self.P = x, P
        self.time_s = None if state["time_s"] is None else float(state["time_s"])
        last = state["last_accepted_s"]
        self.last_accepted_s = None if last is None else float(last)
        self.accepted = int(state["accepted"])
        self.refused = int(state["refused"])
        self.refused_in_row = int(state["refused_in_row"])

    # --- prediction ----------------------------------------------------------------------
    def _transition(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(F, Q) over ``dt_s`` seconds."""
        p = self.params
        dt_h = max(dt_s, 0.0) / SECONDS_PER_HOUR
        if p.kind == "bias":
            if p.reversion_tau_s is None:
                return np.eye(1), np.array([[p.process_um2_per_h * dt_h]])
            tau_h = p.reversion_tau_s / SECONDS_PER_HOUR
            a = math.exp(-dt_h / tau_h)
            return np.array([[a]]), np.array([[p.process_um2_per_h * tau_h / 2 * (1 - a * a)]])
        if p.kind == "bias-gain":
            return np.eye(2), np.diag([p.process_um2_per_h * dt_h, p.gain_process_per_h * dt_h])
        F = np.array([[1.0, dt_h], [0.0, 1.0]])
        qr = p.rate_process_um2_per_h3
        Q = qr * np.array([[dt_h**3 / 3, dt_h**2 / 2], [dt_h**2 / 2, dt_h]])
        Q[0, 0] += p.process_um2_per_h * dt_h
        return F, Q

    def predicted_residual_um(
        self, time_s: np.ndarray | float, predicted_um: np.ndarray | float | None = None
    ) -> np.ndarray:
        """The filter's estimate of the residual at ``time_s`` (≥ the last probe), unbounded.

        ``predicted_um``: the model's prediction at those times (µm); needed by
        ``bias-gain`` (see :attr:`needs_prediction`), ignored by the other kinds.
        """
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        if self.time_s is None:
            return np.zeros(t.shape)
        dt_h = np.maximum(t - self.time_s, 0.0) / SECONDS_PER_HOUR
        p = self.params
        if p.kind == "bias":
            if p.reversion_tau_s is None:
                return np.full(t.shape, self.x[0])
            return self.x[0] * np.exp(-dt_h * SECONDS_PER_HOUR / p.reversion_tau_s)
        if p.kind == "bias-gain":
            if predicted_um is None:
                raise ValueError("online correction bias-gain needs the model's prediction")
            y = np.broadcast_to(np.asarray(predicted_um, dtype=float), t.shape)
            return self.x[0] + self.x[1] * y
        return self.x[0] + self.x[1] * dt_h

    def correction_at(
        self, time_s: np.ndarray | float, predicted_um: np.ndarray | float | None = None
    ) -> np.ndarray:
        """The correction to add to the model's prediction (µm): bounded, decayed in silence.

        ``predicted_um`` as for :meth:`predicted_residual_um`; for ``bias-gain`` a
        prediction that is not finite gives no correction there (0 µm).
        """
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        if self.last_accepted_s is None:
            return np.zeros(t.shape)
        value = self.predicted_residual_um(t, predicted_um)
        value = np.where(np.isfinite(value), value, 0.0)
        p = self.params
        silent_s = t - self.last_accepted_s - p.decay_after_s
        value = value * np.exp(-np.maximum(silent_s, 0.0) / p.decay_tau_s)
        return np.clip(value, -p.bound_um, p.bound_um)

    def added_variance_um2(self, time_s: float, predicted_um: float | None = None) -> float:
        """How much the variance of the applied correction has grown since the last probe
        (µm²): H P(t) Hᵀ − H P Hᵀ, P(t) the filter's predicted covariance at ``time_s``,
        times the square of the silence decay (a decayed correction carries less of it).

        0 before any accepted probe (no correction applied) and right at a probe; it grows
        with the time since the last probe as the process noise says the residual moves.
        ``predicted_um`` as for :meth:`predicted_residual_um` (``bias-gain``).
        """
        if self.last_accepted_s is None or self.time_s is None:
            return 0.0
        if self.needs_prediction and (predicted_um is None or not math.isfinite(predicted_um)):
            return 0.0
        grown = self._grown_variance(max(time_s - self.time_s, 0.0), predicted_um)
        p = self.params
        silent_s = time_s - self.last_accepted_s - p.decay_after_s
        decay = math.exp(-max(silent_s, 0.0) / p.decay_tau_s) if silent_s > 0.0 else 1.0
        return max(grown, 0.0) * decay * decay

    def _grown_variance(self, dt_s: float, predicted_um: float | None) -> float:
        """H (F P Fᵀ + Q) Hᵀ − H P Hᵀ over ``dt_s`` written out per kind (µm²): the same
        figure as :meth:`_transition` gives, without a matrix product on every cycle."""
        p, P = self.params, self.P
        dt_h = dt_s / SECONDS_PER_HOUR
        if p.kind == "bias":
            if p.reversion_tau_s is None:
                return p.process_um2_per_h * dt_h
            tau_h = p.reversion_tau_s / SECONDS_PER_HOUR
            a2 = math.exp(-2.0 * dt_h / tau_h)
            return (a2 - 1.0) * float(P[0, 0]) + p.process_um2_per_h * tau_h / 2 * (1 - a2)
        if p.kind == "bias-gain":
            y = float(predicted_um or 0.0)
            return (p.process_um2_per_h + y * y * p.gain_process_per_h) * dt_h
        cross, rate = float(P[0, 1]), float(P[1, 1])
        return (
            2.0 * dt_h * cross
            + dt_h * dt_h * rate
            + p.rate_process_um2_per_h3 * dt_h**3 / 3.0
            + p.process_um2_per_h * dt_h
        )

    # --- a probe -------------------------------------------------------------------------
    def update(
        self, time_s: float, residual_um: float, predicted_um: float | None = None
    ) -> ProbeOutcome:
        """Take one probe: the model's residual (µm) measured at ``time_s``.

        ``predicted_um``: the model's prediction the residual was taken from (µm),
        needed by ``bias-gain`` and ignored by the other kinds.

        Refused (state unchanged, counted) when not finite, earlier than the
        state, or outside the innovation test; see the module docstring.
        """
        p = self.params
        if not math.isfinite(residual_um) or not math.isfinite(time_s):
            self.refused += 1
            return ProbeOutcome(time_s, residual_um, math.nan, math.nan, False, "not a number")
        if self.needs_prediction and (predicted_um is None or not math.isfinite(predicted_um)):
            self.refused += 1
            return ProbeOutcome(
                time_s, residual_um, math.nan, math.nan, False, "no model prediction"
            )
        if self.time_s is not None and time_s < self.time_s:
            self.refused += 1
            return ProbeOutcome(
                time_s, residual_um, math.nan, math.nan, False, "earlier than the last probe"
            )
        F, Q = self._transition(0.0 if self.time_s is None else time_s - self.time_s)
        x_pred = F @ self.x
        P_pred = F @ self.P @ F.T + Q
        R = p.probe_noise_um**2
        H = self._h(predicted_um)
        S = float(H @ P_pred @ H + R)
        expected = float(H @ x_pred)
        innovation = float(residual_um - expected)
        sigma = math.sqrt(S)
        if abs(innovation) > p.outlier_sigma * sigma:
            self.refused_in_row += 1
            if self.refused_in_row < p.reset_after_refusals:
                self.refused += 1
                return ProbeOutcome(
                    time_s,
                    residual_um,
                    expected,
                    sigma,
                    False,
                    f"outlier: {innovation:+.2f} µm from the prediction, more than "
                    f"{p.outlier_sigma:g} σ ({sigma:.2f} µm)",
                )
            # Several refusals in a row: the machine has changed; start again from this probe.
            P_pred = P_pred + self._prior()
            S = float(H @ P_pred @ H + R)
            reason = f"accepted after {self.refused_in_row} outliers in a row: filter restarted"
        else:
            reason = "accepted"
        gain = P_pred @ H / S
        self.x = x_pred + gain * innovation
        identity_minus = np.eye(self.size) - np.outer(gain, H)
        # Joseph form: stays symmetric positive semi-definite in floating point.
        self.P = identity_minus @ P_pred @ identity_minus.T + np.outer(gain, gain) * R
        self.time_s = float(time_s)
        self.last_accepted_s = float(time_s)
        self.accepted += 1
        self.refused_in_row = 0
        return ProbeOutcome(time_s, residual_um, expected, sigma, True, reason)
