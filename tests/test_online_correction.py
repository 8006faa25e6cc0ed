"""The online correction's Kalman filter, step by step, and its safety rules.

The first tests check single filter steps against numbers worked out by hand;
the safety tests run the correction through the same compensation policy
(clamp, slew limit, deadband) the runtime writes through.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gateway.compensation import CompensationLimits, CompensationPolicy
from models.online_correction import CorrectionParams, OnlineCorrection

HOUR_S = 3600.0


def bias_filter(**overrides) -> OnlineCorrection:
    values = {
        "process_um2_per_h": 1.0,
        "probe_noise_um": 1.0,
        "prior_um": 2.0,
        "outlier_sigma": 4.0,
        "bound_um": 20.0,
        "decay_after_s": 4 * HOUR_S,
        "decay_tau_s": HOUR_S,
    }
    return OnlineCorrection(CorrectionParams(**(values | overrides)))


def test_no_probe_no_correction():
    f = bias_filter()
    assert f.correction_at(np.array([0.0, 1e6])).tolist() == [0.0, 0.0]


def test_first_probe_step_by_hand():
    # P⁻ = prior² = 4 (no time has passed), R = 1: K = 4/5, x = 0.8·5 = 4, P = (1 − K)·4 = 0.8.
    f = bias_filter()
    outcome = f.update(0.0, 5.0)
    assert outcome.accepted
    assert outcome.innovation_sigma_um == pytest.approx(math.sqrt(5.0))
    assert f.x[0] == pytest.approx(4.0)
    assert f.P[0, 0] == pytest.approx(0.8)
    assert f.correction_at(0.0)[0] == pytest.approx(4.0)


def test_second_probe_adds_process_noise_by_hand():
    # After 2 h: P⁻ = 0.8 + 1·2 = 2.8; K = 2.8/3.8; x = 4 + K·(6 − 4).
    f = bias_filter()
    f.update(0.0, 5.0)
    f.update(2 * HOUR_S, 6.0)
    gain = 2.8 / 3.8
    assert f.x[0] == pytest.approx(4.0 + gain * 2.0)
    assert f.P[0, 0] == pytest.approx((1 - gain) * 2.8)


def test_random_walk_holds_between_probes_and_mean_reversion_decays():
    walk = bias_filter()
    walk.update(0.0, 5.0)
    assert walk.correction_at(np.array([0.0, HOUR_S, 2 * HOUR_S])) == pytest.approx([4.0] * 3)
    reverting = bias_filter(reversion_tau_s=HOUR_S)
    reverting.update(0.0, 5.0)
    assert reverting.correction_at(HOUR_S)[0] == pytest.approx(4.0 * math.exp(-1.0))


def test_mean_reverting_process_noise_by_hand():
    # OU over Δ = τ = 1 h: a = e⁻¹, Q = q τ/2 (1 − a²), P⁻ = a² P + Q.
    f = bias_filter(reversion_tau_s=HOUR_S)
    f.update(0.0, 5.0)
    a = math.exp(-1.0)
    expected_p = a * a * 0.8 + 0.5 * (1 - a * a)
    outcome = f.update(HOUR_S, 4.0 * a)  # exactly the prediction: the state does not move
    assert outcome.predicted_um == pytest.approx(4.0 * a)
    assert outcome.innovation_sigma_um == pytest.approx(math.sqrt(expected_p + 1.0))
    assert f.x[0] == pytest.approx(4.0 * a)


def test_bias_rate_extrapolates_a_drift():
    params = CorrectionParams(
        kind="bias-rate",
        process_um2_per_h=0.0,
        rate_process_um2_per_h3=0.01,
        probe_noise_um=0.01,
        prior_um=10.0,
        outlier_sigma=10.0,
    )
    f = OnlineCorrection(params)
    for hour in range(6):
        assert f.update(hour * HOUR_S, 2.0 * hour).accepted  # the residual grows 2 µm/h
    assert f.x[1] == pytest.approx(2.0, abs=0.05)
    assert f.correction_at(6.5 * HOUR_S)[0] == pytest.approx(13.0, abs=0.2)


def test_outlier_is_refused_counted_and_leaves_the_state():
    f = bias_filter(probe_noise_um=0.3)
    for hour in range(4):
        f.update(hour * HOUR_S, 3.0)
    before = f.export_state()
    outcome = f.update(4 * HOUR_S, 33.0)  # a chip under the probe: +30 µm
    assert not outcome.accepted and "outlier" in outcome.reason
    assert f.refused == 1
    after = f.export_state()
    assert (after["x"], after["P"], after["time_s"]) == (before["x"], before["P"], before["time_s"])
    assert f.update(5 * HOUR_S, 3.1).accepted  # the next good probe is taken as usual
    assert f.refused_in_row == 0


def test_two_outliers_in_a_row_restart_the_filter():
    f = bias_filter(probe_noise_um=0.3)
    for hour in range(4):
        f.update(hour * HOUR_S, 3.0)
    assert not f.update(4 * HOUR_S, 15.0).accepted
    outcome = f.update(5 * HOUR_S, 15.0)  # the machine really changed
    assert outcome.accepted and "restarted" in outcome.reason
    assert f.correction_at(5 * HOUR_S)[0] > 12.0


def test_not_a_number_and_time_going_back_are_refused():
    f = bias_filter()
    f.update(HOUR_S, 2.0)
    assert not f.update(2 * HOUR_S, math.nan).accepted
    assert not f.update(0.0, 2.0).accepted
    assert f.refused == 2 and f.accepted == 1


def test_correction_is_bounded():
    f = bias_filter(bound_um=5.0, prior_um=100.0, probe_noise_um=0.1)
    f.update(0.0, 40.0)
    assert f.x[0] > 39.0  # the estimate itself is not clipped…
    assert f.correction_at(0.0)[0] == 5.0  # …what is applied is
    g = bias_filter(bound_um=5.0, prior_um=100.0, probe_noise_um=0.1)
    g.update(0.0, -40.0)
    assert g.correction_at(0.0)[0] == -5.0


def test_silence_decays_the_correction_as_configured():
    f = bias_filter(decay_after_s=2 * HOUR_S, decay_tau_s=0.5 * HOUR_S, prior_um=100.0)
    f.update(0.0, 10.0)
    held = f.correction_at(0.0)[0]
    at = np.array([1.0, 2.0, 2.5, 3.0, 5.0]) * HOUR_S
    expected = held * np.exp(-np.maximum(at - 2 * HOUR_S, 0.0) / (0.5 * HOUR_S))
    assert f.correction_at(at) == pytest.approx(expected)
    assert abs(f.correction_at(12 * HOUR_S)[0]) < 1e-6  # long silence: back to zero
    f.update(12 * HOUR_S, 10.0)  # a new probe ends the silence
    assert f.correction_at(12 * HOUR_S)[0] > 9.0


def test_parameters_and_state_round_trip_as_plain_json():
    import json

    params = CorrectionParams(kind="bias-rate", rate_process_um2_per_h3=0.5, reversion_tau_s=None)
    assert CorrectionParams.from_dict(json.loads(json.dumps(params.as_dict()))) == params
    f = OnlineCorrection(params)
    f.update(0.0, 1.0)
    f.update(HOUR_S, 2.0)
    g = OnlineCorrection(params)
    g.import_state(json.loads(json.dumps(f.export_state())))
    assert g.correction_at(2 * HOUR_S)[0] == pytest.approx(f.correction_at(2 * HOUR_S)[0])


def test_bad_parameters_are_refused_with_their_name():
    with pytest.raises(ValueError, match="bound_um"):
        CorrectionParams(bound_um=0.0)
    with pytest.raises(ValueError, match="kind"):
        CorrectionParams(kind="gain")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown parameter"):
        CorrectionParams.from_dict({"bias_um": 1.0})


# --- through the compensation policy, as the runtime writes ---------------------------------


def run_cycles(
    correction: OnlineCorrection,
    probes: dict[int, float],
    cycles: int,
    cycle_s: float = 60.0,
    predicted_um: float = 10.0,
    limits: CompensationLimits | None = None,
) -> list[float]:
    """Applied compensation per cycle: prediction + correction through clamp/slew/deadband.

    ``probes`` maps a cycle number to the real error then; the residual given to the
    filter is the real error minus the prediction (no compensation feedback here:
    the probe sees the machine's own error, as in ``replay``).
    """
    policy = CompensationPolicy(limits or CompensationLimits(clamp_um=50.0, slew_um_per_min=5.0))
    applied = []
    for k in range(cycles):
        now = k * cycle_s
        if k in probes:
            correction.update(now, probes[k] - predicted_um)
        decision = policy.decide(now, predicted_um + correction.correction_at(now)[0])
        if decision.write:
            policy.confirm(now, decision.target_um)
        applied.append(policy.applied_um)
    return applied


def test_a_probe_outlier_moves_the_applied_compensation_by_less_than_1um():
    params = CorrectionParams(process_um2_per_h=1.0, probe_noise_um=0.3, outlier_sigma=4.0)
    clean = {k: 12.0 for k in range(0, 600, 60)}  # the real error: 12 µm, a probe every hour
    chipped = clean | {300: 42.0}  # once, +30 µm (a chip under the probe)
    reference = run_cycles(OnlineCorrection(params), clean, 600)
    with_chip_filter = OnlineCorrection(params)
    with_chip = run_cycles(with_chip_filter, chipped, 600)
    assert with_chip_filter.refused == 1
    assert max(abs(a - b) for a, b in zip(with_chip, reference, strict=True)) < 1.0
    assert reference[-1] == pytest.approx(12.0, abs=0.6)  # the correction itself works


def test_the_policy_clamp_still_bounds_the_corrected_value():
    params = CorrectionParams(bound_um=30.0, prior_um=100.0, probe_noise_um=0.1)
    limits = CompensationLimits(clamp_um=15.0, slew_um_per_min=100.0)
    applied = run_cycles(OnlineCorrection(params), {0: 60.0}, 30, limits=limits)
    assert max(applied) <= 15.0
    assert applied[-1] == pytest.approx(15.0, abs=1e-3)


# --- the machines[].online_correction config section ----------------------------------------

CONFIG = """\
machines:
  - id: vmc-1
    transmitters:
      - name: bus1
        tcp: {host: 127.0.0.1, port: 5020}
        devices:
          - {device_id: 1, channels: [T1, T2]}
    cnc:
      opcua: {endpoint: "opc.tcp://127.0.0.1:4840/cnc"}
    compensation: {macro: 500, PROBE}
    online_correction:
      enabled: true
      bound_um: BOUND
      decay_after_s: 7200
    models:
      store: STORE
"""


def load_online(tmp_path, probe: str = "probe_macro: 510", bound: str = "8"):
    from gateway.config import load_config

    path = tmp_path / "config.yaml"
    text = CONFIG.replace("PROBE", probe).replace("BOUND", bound)
    path.write_text(text.replace("STORE", str(tmp_path / "models")), encoding="utf-8")
    return path, load_config(path)


def test_config_section_gives_the_filter_its_limits(tmp_path):
    _, config = load_online(tmp_path)
    params = config.machines[0].online_correction.params()
    assert (params.bound_um, params.decay_after_s) == (8.0, 7200.0)
    assert params.outlier_sigma == CorrectionParams().outlier_sigma  # the documented default


def test_config_refuses_a_correction_without_probe_or_with_a_bad_bound(tmp_path):
    from gateway.config import ConfigError

    with pytest.raises(ConfigError, match=r"config.yaml:2: machines\[0\]: .*probe_macro"):
        load_online(tmp_path, probe="clamp_um: 40")
    with pytest.raises(
        ConfigError, match=r"config.yaml:13: machines\[0\].online_correction.bound_um"
    ):
        load_online(tmp_path, bound="0")


def test_the_correction_is_logged_with_the_cycle():
    from gateway.timeseries import points_from_record
    from tests.records import written_record

    record = written_record(
        "vmc-1", 60.0, {}, 12.5, speed_rpm=1000.0, regime=None, predicted_um=10.0, correction_um=2.5
    )
    assert points_from_record(record)[0].fields["correction_um"] == 2.5
    record.correction_um = None  # no correction (off, or no prediction): no field
    assert "correction_um" not in points_from_record(record)[0].fields
