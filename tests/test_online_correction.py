"""The online correction's Kalman filter, step by step, and its safety rules.

The first tests check single filter steps against numbers worked out by hand;
the safety tests run the correction through the same compensation policy
(clamp, slew limit, deadband) the runtime writes through.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gateway.limits import CompensationLimits
from gateway.live.writeback import CompensationPolicy
from models.online.correction import CorrectionParams, OnlineCorrection

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


# --- bias-gain: a gain error on the model's prediction ----------------------------------------


def gain_filter(**overrides) -> OnlineCorrection:
    values = {
        "kind": "bias-gain",
        "process_um2_per_h": 0.01,
        "gain_process_per_h": 1e-4,
        "probe_noise_um": 0.1,
        "prior_um": 5.0,
        "gain_prior": 0.5,
        "outlier_sigma": 4.0,
        "bound_um": 20.0,
    }
    return OnlineCorrection(CorrectionParams(**(values | overrides)))


def warm_up_um(time_s: np.ndarray) -> np.ndarray:
    """A model's prediction through a warm-up and a speed change (µm)."""
    hours = np.asarray(time_s) / HOUR_S
    return 25.0 * (1.0 - np.exp(-hours / 1.5)) - 8.0 * (hours > 4.0) * (1 - np.exp(4.0 - hours))


def test_bias_gain_first_probe_step_by_hand():
    # P⁻ = diag(5², 0.5²), H = [1, ŷ = 10], R = 0.1²: S = 25 + 25 + 0.01 = 50.01,
    # K = P⁻Hᵀ/S = [25, 2.5]/S, x = K·6 for a residual of 6 µm.
    f = gain_filter()
    outcome = f.update(0.0, 6.0, predicted_um=10.0)
    assert outcome.accepted
    assert outcome.innovation_sigma_um == pytest.approx(math.sqrt(50.01))
    assert f.x == pytest.approx([25.0 * 6 / 50.01, 2.5 * 6 / 50.01])
    # Between probes the correction is b + g·ŷ at the prediction then.
    expected = f.x[0] + f.x[1] * np.array([10.0, 20.0])
    assert f.correction_at([0.0, 60.0], predicted_um=[10.0, 20.0]) == pytest.approx(expected)


def test_bias_gain_tracks_a_pure_gain_error_between_probes():
    """The model grows 20 % too little: a bias filter lags every change of the prediction
    by one probe; the gain state carries it between probes."""
    time_s = np.arange(0.0, 8 * HOUR_S, 60.0)
    predicted = warm_up_um(time_s)
    residual = 0.2 * predicted
    probes = range(60, time_s.size, 60)  # one an hour
    gain, bias = gain_filter(), bias_filter(probe_noise_um=0.1, process_um2_per_h=4.0)
    for k in probes:
        assert gain.update(time_s[k], residual[k], predicted_um=predicted[k]).accepted
        assert bias.update(time_s[k], residual[k]).accepted
    assert gain.x[1] == pytest.approx(0.2, abs=0.01)
    assert abs(gain.x[0]) < 0.2
    # Replayed causally, probe by probe: after the third probe the gain kind is within 0.15 µm
    # everywhere; the bias kind misses by the change of 0.2·ŷ since the last probe.
    replay = {"gain": gain_filter(), "bias": bias_filter(probe_noise_um=0.1, process_um2_per_h=4.0)}
    errors = {name: [] for name in replay}
    starts = list(probes)
    for start, end in zip(starts, [*starts[1:], time_s.size], strict=True):
        for name, f in replay.items():
            f.update(time_s[start], residual[start], predicted_um=predicted[start])
            at = f.correction_at(time_s[start:end], predicted_um=predicted[start:end])
            if start >= starts[2]:
                errors[name].append(np.max(np.abs(residual[start:end] - at)))
    assert max(errors["gain"]) < 0.15
    assert max(errors["bias"]) > 0.8


def test_bias_gain_refuses_an_outlier_once_and_moves_the_correction_by_less_than_1um():
    time_s = np.arange(0.0, 10 * HOUR_S, 60.0)
    predicted = warm_up_um(time_s)
    real_residual = 1.0 + 0.15 * predicted
    probes = list(range(60, time_s.size, 60))
    chip = probes[4]

    def corrections(chipped: bool) -> tuple[np.ndarray, OnlineCorrection]:
        f = gain_filter(process_um2_per_h=1.0, gain_process_per_h=1e-3, probe_noise_um=0.3)
        applied = np.zeros(time_s.size)
        for start, end in zip(probes, [*probes[1:], time_s.size], strict=True):
            z = real_residual[start] + (30.0 if chipped and start == chip else 0.0)
            f.update(time_s[start], z, predicted_um=predicted[start])
            applied[start:end] = f.correction_at(time_s[start:end], predicted[start:end])
        return applied, f

    clean, _ = corrections(False)
    with_chip, f = corrections(True)
    assert f.refused == 1
    assert np.max(np.abs(with_chip - clean)) < 1.0
    assert np.max(np.abs(clean[probes[3] :] - real_residual[probes[3] :])) < 0.6


def test_bias_gain_is_bounded_and_decays_in_silence():
    f = gain_filter(bound_um=5.0, prior_um=100.0, gain_prior=5.0, decay_after_s=HOUR_S)
    f.update(0.0, 2.0, predicted_um=10.0)
    f.update(HOUR_S, 60.0, predicted_um=30.0)  # a residual of 60 µm: b + g·ŷ far past 5 µm
    assert f.predicted_residual_um(HOUR_S, 30.0)[0] > 50.0
    assert f.correction_at(HOUR_S, 30.0)[0] == 5.0
    assert f.correction_at(HOUR_S, -30.0)[0] == -5.0  # g·ŷ < 0 for a negative prediction
    inside = (3.0 - f.x[0]) / f.x[1]  # the prediction at which b + g·ŷ = 3 µm
    assert f.correction_at(HOUR_S, inside)[0] == pytest.approx(3.0)
    at = np.array([1.5, 2.0, 3.0]) * HOUR_S  # silent since the last probe at 1 h
    expected = 3.0 * np.exp(-np.maximum(at - 2 * HOUR_S, 0.0) / HOUR_S)
    assert f.correction_at(at, inside) == pytest.approx(expected)
    assert abs(f.correction_at(20 * HOUR_S, 30.0)[0]) < 1e-6


def test_bias_gain_needs_the_prediction():
    f = gain_filter()
    outcome = f.update(0.0, 2.0)
    assert not outcome.accepted and "prediction" in outcome.reason
    assert not f.update(0.0, 2.0, predicted_um=math.nan).accepted
    assert f.refused == 2
    assert f.correction_at(0.0)[0] == 0.0  # nothing accepted yet: no correction at all
    f.update(0.0, 2.0, predicted_um=4.0)
    with pytest.raises(ValueError, match="prediction"):
        f.correction_at(60.0)
    assert f.correction_at([60.0, 120.0], [math.nan, 4.0])[0] == 0.0  # no prediction there


def test_bias_gain_parameters_and_state_round_trip_as_plain_json():
    import json

    params = CorrectionParams(kind="bias-gain", gain_process_per_h=0.01, gain_prior=0.3)
    stored = json.loads(json.dumps(params.as_dict()))
    assert CorrectionParams.from_dict(stored) == params
    # The noise a model stores reaches the runtime's parameters; the limits stay the machine's.
    taken = CorrectionParams(bound_um=7.0).with_noise_of(stored)
    assert (taken.kind, taken.gain_process_per_h, taken.gain_prior) == ("bias-gain", 0.01, 0.3)
    assert taken.bound_um == 7.0
    f = OnlineCorrection(params)
    f.update(0.0, 1.0, predicted_um=5.0)
    f.update(HOUR_S, 3.0, predicted_um=15.0)
    g = OnlineCorrection(params)
    g.import_state(json.loads(json.dumps(f.export_state())))
    assert g.correction_at(2 * HOUR_S, 12.0)[0] == pytest.approx(
        f.correction_at(2 * HOUR_S, 12.0)[0]
    )
    with pytest.raises(ValueError, match="does not fit kind 'bias'"):
        OnlineCorrection(CorrectionParams()).import_state(f.export_state() | {"x": [1.0, 2.0]})


def test_the_runtime_gives_a_bias_gain_filter_the_prediction():
    """The machine loop's two steps: the residual of a probe with the prediction it was taken
    from, and the correction at this cycle's prediction."""
    from types import SimpleNamespace

    from gateway.live.loop import MachineLoop

    params = CorrectionParams(
        kind="bias-gain", process_um2_per_h=0.0, gain_process_per_h=0.0, prior_um=0.01,
        gain_prior=1.0, probe_noise_um=0.01,
    )  # fmt: skip
    loop = SimpleNamespace(
        online=OnlineCorrection(params),
        _probe_basis=None,
        config=SimpleNamespace(id="m1"),
        _online_params=lambda banked: params,
    )
    cycle = SimpleNamespace(applied_um=10.0, probe_error_um=None, probe_refused=None)
    MachineLoop._online_update(loop, 0.0, 10.0, cycle)  # predicted 10 µm, applied 10 µm
    # The probe then measures 2 µm left over with 10 µm applied: residual 2 µm at ŷ = 10 µm.
    probe = SimpleNamespace(applied_um=20.0, probe_error_um=2.0, probe_refused=None)
    MachineLoop._online_update(loop, 60.0, 20.0, probe)
    assert probe.probe_refused is False
    assert loop.online.x[1] == pytest.approx(0.2, abs=1e-3)  # the gain, not a 2 µm bias
    record = SimpleNamespace(correction_um=None, interval_um=None)
    corrected = MachineLoop._corrected(loop, 120.0, None, 30.0, record)
    assert record.correction_um == pytest.approx(6.0, abs=0.01)  # 0.2 × 30 µm
    assert corrected == pytest.approx(36.0, abs=0.01)


def test_bad_parameters_are_refused_with_their_name():
    with pytest.raises(ValueError, match="bound_um"):
        CorrectionParams(bound_um=0.0)
    with pytest.raises(ValueError, match="kind"):
        CorrectionParams(kind="gain")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown parameter"):
        CorrectionParams.from_dict({"bias_um": 1.0})
    with pytest.raises(ValueError, match="gain_prior"):
        CorrectionParams(kind="bias-gain", gain_prior=0.0)
    with pytest.raises(ValueError, match="gain_process_per_h"):
        CorrectionParams(kind="bias-gain", gain_process_per_h=-1.0)


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
    from gateway.outputs.points import points_from_record
    from tests.records import written_record

    record = written_record(
        "vmc-1", 60.0, {}, 12.5, speed_rpm=1000.0, regime=None, predicted_um=10.0, correction_um=2.5
    )
    assert points_from_record(record)[0].fields["correction_um"] == 2.5
    record.correction_um = None  # no correction (off, or no prediction): no field
    assert "correction_um" not in points_from_record(record)[0].fields
