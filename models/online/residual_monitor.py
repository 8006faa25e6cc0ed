"""Sequential tests on the probe residuals: is there structure the online correction misses?

Every probe gives the online filter (:mod:`models.online.correction`) an
*innovation*: the probe's residual minus what the filter predicted, with its
standard deviation √S. When the model and the filter describe the machine, the
standardised innovations z = innovation / √S are independent N(0, 1). An effect
the model lacks leaves structure in them:

- a **trend** of the residual (creep, a growing offset) that the random-walk
  bias can only follow from behind: z keeps one sign, its mean moves off 0;
- a **dependence on speed**, or on the **time since the last speed change** (a
  heat path with its own lag, a speed-direct growth): z follows the speed
  programme.

Two tests run on z, per regime (the speed regime the runtime selected), and
either one raises an :class:`Alarm`:

1. **Two-sided CUSUM (Page)** with reference value k (σ units):
   S⁺ₙ = max(0, S⁺ₙ₋₁ + zₙ − k), S⁻ₙ = max(0, S⁻ₙ₋₁ − zₙ − k), alarm when
   either exceeds h. Under the null its average run length (probes to a false
   alarm) is, by Siegmund's approximation for one side,
   ARL₁(h) = (e^{2k b} − 2k b − 1) / (2k²), b = h + 1.166, and
   ARL = ARL₁ / 2 for the two-sided scheme. h is solved from the target ARL.
2. **Window regression**: over the last ``window_probes`` probes of a regime,
   z is regressed on ``REGRESSORS`` (a mean, a linear trend in time, the speed,
   and the last speed step times e^{−Δt/τ} for τ = 15 min and 1 h, Δt the time
   since that step). Under the null, z is N(0, 1) with known variance, so the
   regression sum of squares zᵀH z is χ² with p (the design's rank) degrees of
   freedom. The test is made at every probe once the window is full; its level
   α is set by Bonferroni over every test of a month, so the month's false
   alarms from it are at most its share of the budget (fewer: overlapping
   windows are correlated). A statistically significant fit must also be large
   enough to matter: its fitted values, back in µm (z × √S), must have an RMS of
   at least ``min_effect_um``.

Thresholds come from ``false_alarms_per_month``, the expected number of false
alarms of the two tests together over 30 days of operation at ``probe_period_s``:
half of it for the CUSUM, half for the regression (a union bound). An alarm
does not change the compensation: it starts a residual analysis of the logged
history, whose own rules (:mod:`models.analysis.search`) decide whether an effect is
proposed. :func:`simulated_false_alarms` counts alarms on simulated null
innovations, so the stated rate can be checked.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

SECONDS_PER_MONTH = 30 * 86400.0
SIEGMUND_OFFSET = 1.166  # the CUSUM's overshoot correction (Siegmund 1985)
TRANSIENT_TAUS_S = (900.0, 3600.0)
REGRESSORS = (
    "mean",
    "trend_h",
    "speed_krpm",
    *(f"speed_step_krpm_x_exp(-dt/{tau:g}s)" for tau in TRANSIENT_TAUS_S),
)
ALL_REGIMES = "all"


class MonitorParams(BaseModel):
    """Design of the sequential tests (units in the names); the config's ``monitor:``
    section (:class:`gateway.config.MonitorSection`) is this schema plus the gateway's keys."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: the probe cycle's period the thresholds are set for, s
    probe_period_s: float = Field(default=300.0, gt=0)
    #: expected false alarms of the tests together per 30 days of operation
    false_alarms_per_month: float = Field(default=1.0, gt=0)
    cusum_k_sigma: float = Field(default=0.5, gt=0)
    #: probes in the window regression: at least twice its regressors
    window_probes: int = Field(default=36, ge=2 * len(REGRESSORS))
    min_effect_um: float = Field(default=0.3, gt=0)

    @property
    def probes_per_month(self) -> float:
        return SECONDS_PER_MONTH / self.probe_period_s

    @property
    def cusum_arl_probes(self) -> float:
        """Average probes between false CUSUM alarms: its half of the budget."""
        return self.probes_per_month / (0.5 * self.false_alarms_per_month)

    @property
    def cusum_h_sigma(self) -> float:
        return cusum_threshold(self.cusum_k_sigma, self.cusum_arl_probes)

    @property
    def regression_alpha(self) -> float:
        """Level of one window test: its half of the budget over a month's tests (Bonferroni)."""
        return min(0.5 * self.false_alarms_per_month / self.probes_per_month, 0.5)

    def describe(self) -> dict[str, Any]:
        return self.model_dump() | {
            "cusum_h_sigma": self.cusum_h_sigma,
            "cusum_arl_probes": self.cusum_arl_probes,
            "regression_alpha": self.regression_alpha,
            "regressors": list(REGRESSORS),
        }


def cusum_arl(k: float, h: float) -> float:
    """Siegmund's approximation of the two-sided CUSUM's in-control ARL (probes)."""
    b = h + SIEGMUND_OFFSET
    one_sided = (math.exp(2 * k * b) - 2 * k * b - 1) / (2 * k * k)
    return one_sided / 2.0


@functools.lru_cache(maxsize=64)
def cusum_threshold(k: float, arl_probes: float) -> float:
    """The h (σ) whose two-sided in-control ARL is ``arl_probes``."""
    from scipy import optimize  # here, not at import: the config loads this module

    highest = 700.0 / (2 * k) - SIEGMUND_OFFSET  # e^{2kb} stays a finite float up to here
    return float(optimize.brentq(lambda h: cusum_arl(k, h) - arl_probes, 0.0, highest))


@dataclass(frozen=True)
class ProbeInnovation:
    """One probe as the monitor sees it (units in the names)."""

    time_s: float
    innovation_um: float
    sigma_um: float  # √S, the innovation's standard deviation
    speed_rpm: float
    speed_step_rpm: float  # the last speed change (new − old), r/min
    since_step_s: float  # time since that change
    regime: str = ALL_REGIMES

    @property
    def z(self) -> float:
        return self.innovation_um / self.sigma_um


@dataclass(frozen=True)
class Alarm:
    """A test found structure: which, where, how strong."""

    test: str  # "cusum+" | "cusum-" | "regression"
    regime: str
    time_s: float
    statistic: float
    threshold: float
    probes: int  # probes of the regime seen so far
    detail: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def describe(self) -> str:
        text = (
            f"{self.test} on regime {self.regime}: {self.statistic:.2f} > "
            f"{self.threshold:.2f} after {self.probes} probes"
        )
        if "effect_rms_um" in self.detail:
            text += f", fitted structure {self.detail['effect_rms_um']:.2f} µm RMS"
        return text


class RegimeTests:
    """CUSUM sums and the regression window of one regime."""

    def __init__(self, params: MonitorParams) -> None:
        self.params = params
        self.window: deque[ProbeInnovation] = deque(maxlen=params.window_probes)
        self.plus = 0.0
        self.minus = 0.0
        self.probes = 0

    def reset(self) -> None:
        self.window.clear()
        self.plus = self.minus = 0.0

    def observe(self, probe: ProbeInnovation) -> Alarm | None:
        p = self.params
        self.probes += 1
        z = probe.z
        self.plus = max(0.0, self.plus + z - p.cusum_k_sigma)
        self.minus = max(0.0, self.minus - z - p.cusum_k_sigma)
        self.window.append(probe)
        h = p.cusum_h_sigma
        for name, value in (("cusum+", self.plus), ("cusum-", self.minus)):
            if value > h:
                return Alarm(name, probe.regime, probe.time_s, value, h, self.probes)
        if len(self.window) == p.window_probes:
            return self._regression(probe)
        return None

    def _regression(self, probe: ProbeInnovation) -> Alarm | None:
        p = self.params
        rows = list(self.window)
        design = regression_design(rows)
        z = np.array([r.z for r in rows])
        sigma = np.array([r.sigma_um for r in rows])
        beta, _, rank, _ = np.linalg.lstsq(design, z, rcond=None)
        fitted = design @ beta
        statistic = float(fitted @ fitted)
        threshold = chi2_threshold(p.regression_alpha, int(rank))
        effect_rms_um = float(np.sqrt(np.mean((fitted * sigma) ** 2)))
        if statistic <= threshold or effect_rms_um < p.min_effect_um:
            return None
        detail = {
            "effect_rms_um": effect_rms_um,
            "degrees_of_freedom": rank,
            "coefficients_sigma": dict(zip(REGRESSORS, (float(b) for b in beta), strict=True)),
        }
        return Alarm(
            "regression", probe.regime, probe.time_s, statistic, threshold, self.probes, detail
        )


@functools.lru_cache(maxsize=64)
def chi2_threshold(alpha: float, degrees_of_freedom: int) -> float:
    """The χ² value exceeded with probability ``alpha`` (cached: one per window rank)."""
    from scipy import stats

    return float(stats.chi2.isf(alpha, degrees_of_freedom))


def regression_design(rows: list[ProbeInnovation]) -> np.ndarray:
    """The window's regressors (``REGRESSORS``), one row per probe."""
    time_h = np.array([r.time_s for r in rows]) / 3600.0
    speed = np.array([r.speed_rpm for r in rows]) / 1000.0
    step = np.array([r.speed_step_rpm for r in rows]) / 1000.0
    since = np.array([r.since_step_s for r in rows])
    columns = [np.ones(len(rows)), time_h - time_h.mean(), speed]
    columns += [step * np.exp(-since / tau) for tau in TRANSIENT_TAUS_S]
    return np.column_stack(columns)


class ResidualMonitor:
    """The tests of the module docstring, per regime; one call per probe."""

    def __init__(self, params: MonitorParams | None = None) -> None:
        self.params = params or MonitorParams()
        self.regimes: dict[str, RegimeTests] = {}
        self.alarms: list[Alarm] = []

    def observe(self, probe: ProbeInnovation) -> Alarm | None:
        if not (math.isfinite(probe.z) and probe.sigma_um > 0):
            return None
        tests = self.regimes.setdefault(probe.regime, RegimeTests(self.params))
        alarm = tests.observe(probe)
        if alarm is not None:
            self.alarms.append(alarm)
            tests.reset()  # a fresh start: the next alarm needs new evidence
        return alarm

    def reset(self) -> None:
        """Forget the evidence of every regime (after a model change)."""
        for tests in self.regimes.values():
            tests.reset()


def simulated_false_alarms(
    params: MonitorParams, months: float, seed: int = 0, step_every_probes: int = 6
) -> dict[str, float]:
    """Alarms on null innovations (z iid N(0, 1)) over ``months`` of probes.

    The speed programme is random (a new speed every ``step_every_probes`` probes
    on average), as the regressors need one; under the null z does not depend on it.
    """
    rng = np.random.default_rng(seed)
    n = round(months * params.probes_per_month)
    monitor = ResidualMonitor(params)
    speed = last_step = 0.0
    step_time = 0.0
    for i in range(n):
        t = i * params.probe_period_s
        if rng.random() < 1.0 / step_every_probes:
            new = float(rng.choice([0.0, 1500.0, 3500.0, 6000.0, 8000.0]))
            last_step, speed, step_time = (
                new - speed,
                new,
                t - rng.uniform(0, params.probe_period_s),
            )
        monitor.observe(
            ProbeInnovation(
                t, float(rng.standard_normal()) * 0.5, 0.5, speed, last_step, t - step_time
            )
        )
    by_test: dict[str, float] = {}
    for alarm in monitor.alarms:
        key = "regression" if alarm.test == "regression" else "cusum"
        by_test[key] = by_test.get(key, 0) + 1
    return {
        "months": months,
        "probes": n,
        "alarms": len(monitor.alarms),
        "alarms_per_month": len(monitor.alarms) / months,
        "cusum": by_test.get("cusum", 0),
        "regression": by_test.get("regression", 0),
    }
