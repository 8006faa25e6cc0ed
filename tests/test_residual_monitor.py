"""The residual monitor's sequential tests: thresholds, false-alarm rate, detection.

Pure maths on synthetic innovations (the end-to-end paths are
``tests/test_monitor_days.py`` and ``tests/test_monitor_loop.py``).
"""

from __future__ import annotations

import numpy as np
import pytest

from models.online.residual_monitor import (
    MonitorParams,
    ProbeInnovation,
    ResidualMonitor,
    cusum_arl,
    cusum_threshold,
    simulated_false_alarms,
)


def test_threshold_inverts_siegmunds_arl():
    h = cusum_threshold(0.5, 17280.0)
    assert cusum_arl(0.5, h) == pytest.approx(17280.0, rel=1e-9)
    assert 8.0 < h < 9.5  # h ≈ 8.6 σ for one false CUSUM alarm per 2 months of 300 s probes


def test_cusum_run_length_under_the_null_matches_the_design():
    """Mean probes to a false CUSUM alarm, simulated, against the design ARL (h from Siegmund)."""
    params = MonitorParams(probe_period_s=300.0, false_alarms_per_month=500.0)
    h, k = params.cusum_h_sigma, params.cusum_k_sigma
    rng = np.random.default_rng(1)
    lengths = []
    for _ in range(400):
        plus = minus = 0.0
        n = 0
        while True:
            n += 1
            z = rng.standard_normal()
            plus, minus = max(0.0, plus + z - k), max(0.0, minus - z - k)
            if plus > h or minus > h:
                break
        lengths.append(n)
    assert np.mean(lengths) == pytest.approx(params.cusum_arl_probes, rel=0.2)


def test_false_alarms_per_month_at_most_the_design():
    params = MonitorParams(false_alarms_per_month=30.0)
    measured = simulated_false_alarms(params, months=2.0, seed=2)
    assert measured["probes"] == 17280
    # The CUSUM's half is Siegmund's (close), the regression's half a Bonferroni bound.
    assert 3.0 <= measured["alarms_per_month"] <= 30.0, measured
    assert measured["cusum"] >= 5


def probes(z: np.ndarray, speed: np.ndarray, sigma_um: float = 0.5) -> list[ProbeInnovation]:
    rows = []
    step, step_s, previous = 0.0, 0.0, speed[0]
    for i, (value, n) in enumerate(zip(z, speed, strict=True)):
        t = 300.0 * i
        if n != previous:
            step, step_s, previous = n - previous, t, n
        rows.append(ProbeInnovation(t, value * sigma_um, sigma_um, n, step, t - step_s))
    return rows


def test_a_one_sigma_mean_shift_alarms_the_cusum_within_a_day():
    rng = np.random.default_rng(3)
    z = rng.standard_normal(300)
    z[100:] += 1.0
    monitor = ResidualMonitor()
    alarms = [
        (i, a) for i, p in enumerate(probes(z, np.full(300, 4000.0))) if (a := monitor.observe(p))
    ]
    assert alarms and alarms[0][1].test == "cusum+"
    assert 100 <= alarms[0][0] <= 100 + 288  # within a day of 300 s probes


def test_a_speed_dependence_alarms_the_regression_only():
    """Mean zero, no trend, but z follows the speed: only the regression sees it."""
    rng = np.random.default_rng(4)
    speed = np.tile(np.repeat([2000.0, 6000.0], 3), 40)
    z = rng.standard_normal(speed.size) + np.where(speed > 4000, 1.2, -1.2)
    monitor = ResidualMonitor()
    alarms = [a for p in probes(z, speed) if (a := monitor.observe(p))]
    assert alarms and alarms[0].test == "regression", alarms
    assert alarms[0].detail["effect_rms_um"] >= 0.3


def test_a_structure_too_small_to_matter_does_not_alarm():
    """The same structure at 0.05 µm of innovation σ: significant, but under min_effect_um."""
    rng = np.random.default_rng(4)
    speed = np.tile(np.repeat([2000.0, 6000.0], 3), 40)
    z = rng.standard_normal(speed.size) + np.where(speed > 4000, 1.2, -1.2)
    monitor = ResidualMonitor()
    for p in probes(z, speed, sigma_um=0.05):
        monitor.observe(p)
    assert monitor.regimes["all"].probes == speed.size
    assert not [a for a in monitor.alarms if a.test == "regression"]


def test_regimes_keep_their_own_evidence():
    monitor = ResidualMonitor()
    rng = np.random.default_rng(5)
    for i, p in enumerate(probes(rng.standard_normal(60) + 1.5, np.full(60, 3000.0))):
        regime = "variable" if i % 2 else "constant"
        monitor.observe(
            ProbeInnovation(
                p.time_s,
                p.innovation_um,
                p.sigma_um,
                p.speed_rpm,
                p.speed_step_rpm,
                p.since_step_s,
                regime,
            )
        )
    assert {a.regime for a in monitor.alarms} == {"variable", "constant"}
