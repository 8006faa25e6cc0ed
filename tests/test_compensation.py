"""Tests for gateway.live.writeback: clamp, slew, deadband, fallback ramp, CNC format."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from gateway.limits import CompensationLimits
from gateway.live.writeback import CompensationPolicy, Decision, ExternalChange

DEFAULT = CompensationLimits()  # ±50 µm, 20 µm/min, deadband 0.5 µm, mm with 4 decimals
NO_HOLD = CompensationLimits(hold_on_loss_s=0.0)  # no prediction: ramp to zero at once


def write_ok(policy: CompensationPolicy, now_s: float, decision: Decision) -> None:
    """What the runtime does after a successful write: confirm the read-back value."""
    if decision.write:
        policy.confirm(now_s, policy.from_cnc(decision.value_cnc))


def settle(policy: CompensationPolicy, start_s: float, predicted_um: float | None) -> float:
    """Run 3 s cycles with successful writes until nothing changes; returns the time."""
    now = start_s
    for _ in range(1000):
        decision = policy.decide(now, predicted_um)
        write_ok(policy, now, decision)
        if not decision.write:
            return now
        now += 3.0
    raise AssertionError("did not settle")


# --- limits -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"clamp_um": 0.0}, "clamp_um"),
        ({"clamp_um": -5.0}, "clamp_um"),
        ({"clamp_um": math.inf}, "clamp_um"),
        ({"clamp_um": 0.05}, "clamp_um"),  # below one CNC step (0.1 µm)
        ({"slew_um_per_min": 0.0}, "slew_um_per_min"),
        ({"slew_um_per_min": math.nan}, "slew_um_per_min"),
        ({"deadband_um": -0.1}, "deadband_um"),
        ({"unit": "in"}, "unit"),
        ({"sign": 0}, "sign"),
        ({"sign": 2}, "sign"),
        ({"decimals": -1}, "decimals"),
        ({"decimals": 2.5}, "decimals"),
        ({"fallback_ramp_um_per_min": 0.0}, "fallback_ramp_um_per_min"),
        ({"hold_on_loss_s": -1.0}, "hold_on_loss_s"),
        ({"hold_on_loss_s": math.inf}, "hold_on_loss_s"),
    ],
)
def test_invalid_limits_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        CompensationLimits(**kwargs)


def test_step_and_ramp_defaults():
    assert DEFAULT.step_um == pytest.approx(0.1)
    assert CompensationLimits(unit="um", decimals=2).step_um == pytest.approx(0.01)
    assert DEFAULT.ramp_um_per_min == 20.0
    assert CompensationLimits(fallback_ramp_um_per_min=5.0).ramp_um_per_min == 5.0


# --- CNC format -------------------------------------------------------------------------


def test_to_and_from_cnc_in_mm():
    policy = CompensationPolicy(DEFAULT)
    assert policy.to_cnc(12.34) == 0.0123
    assert policy.to_cnc(12.36) == 0.0124
    assert policy.to_cnc(-50.0) == -0.05
    assert policy.from_cnc(0.0123) == 12.3
    assert policy.from_cnc(-0.05) == -50.0


def test_sign_minus_one_flips_both_ways():
    policy = CompensationPolicy(CompensationLimits(sign=-1))
    assert policy.to_cnc(12.34) == -0.0123
    assert policy.from_cnc(-0.0123) == 12.3
    assert math.copysign(1.0, policy.to_cnc(0.0)) == 1.0  # never "-0.0" on the CNC
    assert math.copysign(1.0, policy.from_cnc(0.0)) == 1.0


def test_to_and_from_cnc_in_um():
    policy = CompensationPolicy(CompensationLimits(unit="um", decimals=1, sign=-1))
    assert policy.to_cnc(12.34) == -12.3
    assert policy.from_cnc(-12.3) == 12.3
    coarse = CompensationPolicy(CompensationLimits(unit="mm", decimals=2, clamp_um=50.0))
    assert coarse.to_cnc(14.0) == 0.01
    assert coarse.from_cnc(0.01) == 10.0


@pytest.mark.parametrize(("unit", "decimals", "sign"), [("mm", 4, 1), ("mm", 3, -1), ("um", 1, 1)])
def test_round_trip_is_within_half_a_step(unit, decimals, sign):
    limits = CompensationLimits(unit=unit, decimals=decimals, sign=sign)
    policy = CompensationPolicy(limits)
    for um in np.random.default_rng(3).uniform(-60, 60, 500):
        value = policy.to_cnc(float(um))
        assert value == round(value, decimals)
        assert abs(policy.from_cnc(value) - um) <= limits.step_um / 2 + 1e-9
        assert policy.to_cnc(policy.from_cnc(value)) == value


# --- hand-checked sequences -------------------------------------------------------------


def test_first_decision_writes_the_start_value():
    policy = CompensationPolicy(DEFAULT, start_um=7.3)
    decision = policy.decide(100.0, 30.0)
    assert decision == Decision(7.3, True, 0.0073, "first write, slew-limited")
    policy.confirm(100.0, 7.3)
    assert policy.decide(100.0, 7.4).write is False


def test_first_write_is_repeated_until_confirmed():
    policy = CompensationPolicy(DEFAULT, start_um=2.0)
    assert policy.decide(0.0, 2.0).write is True
    policy.reject(0.0, "timeout")
    decision = policy.decide(3.0, 2.0)
    assert decision.write is True and decision.reason == "first write"


def test_slew_20_um_per_min_with_3_s_cycles_steps_1_um():
    policy = CompensationPolicy(DEFAULT)
    targets = []
    for k in range(14):
        now = 3.0 * k
        decision = policy.decide(now, 10.0)
        targets.append((decision.target_um, decision.write, decision.reason))
        write_ok(policy, now, decision)
    assert targets[0] == (0.0, True, "first write, slew-limited")
    assert [t for t, _, _ in targets[1:11]] == [float(k) for k in range(1, 11)]
    assert all(reason == "slew-limited" for _, _, reason in targets[1:10])
    assert targets[10] == (10.0, True, "tracking")
    assert targets[11] == (10.0, False, "within deadband")
    assert policy.applied_um == 10.0


def test_slew_with_1_s_cycles_writes_every_other_cycle():
    """A step (0.33 µm) smaller than the deadband: the budget grows until it is worth writing.

    After 2 s the budget is 0.67 µm: the CNC grid point inside it (0.6 µm) is written,
    never the nearest one (0.7 µm), which would exceed the slew limit.
    """
    policy = CompensationPolicy(DEFAULT)
    written = []
    for k in range(13):
        decision = policy.decide(float(k), 10.0)
        write_ok(policy, float(k), decision)
        if decision.write:
            written.append((k, decision.target_um))
    assert written == [(0, 0.0), (2, 0.6), (4, 1.2), (6, 1.8), (8, 2.4), (10, 3.0), (12, 3.6)]


def test_clamp_at_plus_and_minus():
    policy = CompensationPolicy(DEFAULT, start_um=49.5)
    policy.confirm(0.0, 49.5)
    decision = policy.decide(60.0, 80.0)
    assert decision.target_um == 50.0
    assert decision.value_cnc == 0.05
    assert decision.reason == "clamped at +50.0 µm"
    policy.confirm(60.0, 50.0)
    assert policy.decide(600.0, 1e300).target_um == 50.0
    policy = CompensationPolicy(DEFAULT, start_um=-49.5)
    policy.confirm(0.0, -49.5)
    decision = policy.decide(60.0, -80.0)
    assert (decision.target_um, decision.reason) == (-50.0, "clamped at -50.0 µm")


def test_clamp_is_taken_to_the_cnc_grid():
    """A clamp between two CNC steps: rounding must not carry a value past it."""
    limits = CompensationLimits(clamp_um=12.35, decimals=4)  # step 0.1 µm
    policy = CompensationPolicy(limits, start_um=12.3)
    policy.confirm(0.0, 12.3)
    decision = policy.decide(60.0, 13.0)
    assert decision.target_um == 12.3
    assert abs(policy.from_cnc(decision.value_cnc)) <= 12.35


def test_start_value_outside_the_clamp_is_clamped_at_once():
    policy = CompensationPolicy(DEFAULT, start_um=80.0)
    decision = policy.decide(0.0, 80.0)
    assert decision.target_um == 50.0 and decision.write is True


def test_deadband_suppresses_tiny_changes():
    policy = CompensationPolicy(DEFAULT, start_um=10.0)
    write_ok(policy, 0.0, policy.decide(0.0, 10.0))
    small = policy.decide(60.0, 10.4)
    assert (small.target_um, small.write, small.reason) == (10.4, False, "within deadband")
    assert policy.decide(61.0, 9.6).write is False
    assert policy.decide(62.0, 10.5).write is True
    assert policy.decide(63.0, 9.5).write is True


def test_zero_deadband_writes_every_change():
    policy = CompensationPolicy(CompensationLimits(deadband_um=0.0), start_um=10.0)
    write_ok(policy, 0.0, policy.decide(0.0, 10.0))
    assert policy.decide(60.0, 10.1).write is True
    assert policy.decide(61.0, 10.0).write is False  # no change: nothing to write


def test_failed_write_never_moves_the_applied_value():
    policy = CompensationPolicy(DEFAULT)
    write_ok(policy, 0.0, policy.decide(0.0, 0.0))
    decision = policy.decide(3.0, 10.0)
    assert decision.target_um == 1.0 and decision.write
    policy.reject(3.0, "timeout")
    assert policy.applied_um == 0.0
    assert policy.failed_writes == 1
    assert policy.last_failure == "timeout"
    # The budget counts from the last applied value (6 s -> 2 µm) but a missed
    # cycle adds at most deadband + one CNC step: 0.5 + 0.1 + 1.0 µm.
    decision = policy.decide(6.0, 10.0)
    assert decision.target_um == 1.6
    policy.reject(6.0, "read-back mismatch")
    assert (policy.applied_um, policy.failed_writes) == (0.0, 2)


def test_long_outage_resumes_with_a_ramp_not_a_jump():
    policy = CompensationPolicy(DEFAULT)
    write_ok(policy, 0.0, policy.decide(0.0, 0.0))
    for k in range(1, 100):  # five minutes of failed writes
        policy.decide(3.0 * k, 40.0)
        policy.reject(3.0 * k, "CNC offline")
    decision = policy.decide(300.0, 40.0)
    # Budget: deadband + one CNC step + one cycle of slew (1 µm), not 100 µm banked.
    assert decision.target_um == pytest.approx(1.6)


def test_a_hold_in_the_deadband_does_not_bank_slew():
    policy = CompensationPolicy(DEFAULT, start_um=10.0)
    write_ok(policy, 0.0, policy.decide(0.0, 10.0))
    for k in range(1, 201):  # ten minutes inside the deadband
        assert policy.decide(3.0 * k, 10.3).write is False
    decision = policy.decide(603.0, 30.0)  # e.g. a model switch
    assert decision.target_um == pytest.approx(11.6)  # 10 + 0.5 + 0.1 + 1.0
    assert decision.reason == "slew-limited"


# --- no prediction: ramp to zero, then resume ----------------------------------------------


@pytest.mark.parametrize("missing", [None, math.nan, math.inf, -math.inf])
def test_no_prediction_ramps_to_zero(missing):
    policy = CompensationPolicy(NO_HOLD, start_um=5.0)
    write_ok(policy, 0.0, policy.decide(0.0, 5.0))
    targets = []
    for k in range(1, 8):
        decision = policy.decide(3.0 * k, missing)
        assert decision.reason.startswith("no prediction")
        assert "ramping to zero" in decision.reason
        write_ok(policy, 3.0 * k, decision)
        targets.append(decision.target_um)
    assert targets == [4.0, 3.0, 2.0, 1.0, 0.0, 0.0, 0.0]
    assert policy.applied_um == 0.0


def test_fallback_ramp_rate_and_sign():
    limits = CompensationLimits(fallback_ramp_um_per_min=60.0, hold_on_loss_s=0.0)
    policy = CompensationPolicy(limits, start_um=-9.0)
    write_ok(policy, 0.0, policy.decide(0.0, -9.0))
    targets = []
    for k in range(1, 5):
        decision = policy.decide(3.0 * k, None)
        write_ok(policy, 3.0 * k, decision)
        targets.append(decision.target_um)
    assert targets == [-6.0, -3.0, 0.0, 0.0]


def test_tracking_resumes_when_predictions_return():
    policy = CompensationPolicy(NO_HOLD)
    for k in range(21):  # 0, 1, 2, ... 20 µm
        write_ok(policy, 3.0 * k, policy.decide(3.0 * k, 20.0))
    assert policy.applied_um == 20.0
    for k in range(21, 26):  # 15 s without prediction: 5 µm down
        write_ok(policy, 3.0 * k, policy.decide(3.0 * k, None))
    assert policy.applied_um == 15.0
    now = 78.0
    decision = policy.decide(now, 25.0)
    assert (decision.target_um, decision.reason) == (16.0, "slew-limited")
    write_ok(policy, now, decision)
    settle(policy, now + 3, 25.0)
    assert policy.applied_um == 25.0


def test_no_prediction_holds_then_ramps_at_the_configured_rate():
    limits = CompensationLimits(hold_on_loss_s=60.0, fallback_ramp_um_per_min=10.0)
    policy = CompensationPolicy(limits, start_um=20.0)
    write_ok(policy, 0.0, policy.decide(0.0, 20.0))  # the last cycle with a prediction
    seen = []
    for k in range(1, 8):
        decision = policy.decide(30.0 * k, None)
        write_ok(policy, 30.0 * k, decision)
        seen.append((decision.target_um, decision.write))
    # Held 60 s after the last prediction, then 10 µm/min (5 µm per 30 s cycle) to 0.
    assert seen == [
        (20.0, False),
        (20.0, False),
        (15.0, True),
        (10.0, True),
        (5.0, True),
        (0.0, True),
        (0.0, False),
    ]
    assert policy.decide(240.0, None).reason == "no prediction: ramping to zero, within deadband"


def test_hold_reason_and_restart_when_a_prediction_returns():
    limits = CompensationLimits(hold_on_loss_s=60.0)
    policy = CompensationPolicy(limits, start_um=10.0)
    write_ok(policy, 0.0, policy.decide(0.0, 10.0))
    decision = policy.decide(40.0, math.nan)
    assert decision.reason == "no prediction (nan): holding for 60 s (40 s so far), within deadband"
    assert (decision.target_um, decision.write) == (10.0, False)
    assert policy.decide(50.0, 10.0).reason == "within deadband"  # the prediction is back
    assert policy.decide(100.0, None).target_um == 10.0  # 50 s since: still held
    assert policy.decide(120.0, None).target_um < 10.0  # 70 s since: ramping


def test_ramp_to_zero_writes_the_last_small_step():
    policy = CompensationPolicy(NO_HOLD, start_um=0.3)  # below the 0.5 µm deadband
    write_ok(policy, 0.0, policy.decide(0.0, 0.3))
    decision = policy.decide(3.0, None)
    assert (decision.target_um, decision.write) == (0.0, True)
    policy.confirm(3.0, 0.0)
    assert policy.decide(6.0, None).write is False  # at zero: nothing more to write


def test_disabled_ramps_to_zero_at_the_slew_rate_and_stops_there():
    policy = CompensationPolicy(DEFAULT, start_um=2.5)
    write_ok(policy, 0.0, policy.decide(0.0, 2.5))
    seen = []
    for k in range(1, 6):
        decision = policy.decide(3.0 * k, 30.0, enabled=False)  # the prediction is ignored
        write_ok(policy, 3.0 * k, decision)
        seen.append((decision.target_um, decision.write))
    assert seen == [(1.5, True), (0.5, True), (0.0, True), (0.0, False), (0.0, False)]
    assert decision.reason == "compensation disabled: ramping to zero, within deadband"


def test_hold_while_disabled_banks_no_slew():
    policy = CompensationPolicy(DEFAULT, start_um=5.0)
    write_ok(policy, 0.0, policy.decide(0.0, 5.0))
    for k in range(1, 201):  # ten minutes switched off, CNC left alone
        policy.hold(3.0 * k)
    decision = policy.decide(603.0, 40.0)  # switched on again
    assert decision.target_um == 6.0  # one cycle of slew, not ten minutes


def test_switched_on_after_a_hold_without_prediction_holds_first():
    policy = CompensationPolicy(DEFAULT, start_um=5.0)
    write_ok(policy, 0.0, policy.decide(0.0, 5.0))
    for k in range(1, 201):
        policy.hold(3.0 * k)
    assert "holding" in policy.decide(603.0, None).reason  # not an instant ramp
    assert "ramping" in policy.decide(663.0, None).reason


def test_budget_counts_from_the_confirmed_write_not_the_cycle_start():
    policy = CompensationPolicy(CompensationLimits(deadband_um=0.0), start_um=0.0)
    write_ok(policy, 0.0, policy.decide(0.0, 0.0))
    late = policy.decide(30.6, 40.0)  # this cycle's write went out 0.6 s late
    assert late.target_um == 10.2
    policy.confirm(30.6, 10.2)
    on_time = policy.decide(60.0, 40.0)  # 29.4 s later: 9.8 µm, not 10 µm
    assert on_time.target_um == 20.0
    assert on_time.target_um - 10.2 <= 20.0 * 29.4 / 60.0 + 1e-9


# --- the CNC's value is the truth ---------------------------------------------------------


def test_observe_the_value_the_gateway_applied_changes_nothing():
    policy = CompensationPolicy(DEFAULT, start_um=48.8)
    write_ok(policy, 0.0, policy.decide(0.0, 48.8))
    assert policy.observe(1.0, 0.0488) is None
    assert policy.observe(2.0, 0.04879999905824661) is None  # 0.0488 carried as float32
    assert policy.observe(3.0, 0.04884) is None  # within half a CNC step
    assert (policy.applied_um, policy.external_changes) == (48.8, 0)


def test_observe_an_external_change_reseeds_and_restarts_the_slew_budget():
    policy = CompensationPolicy(DEFAULT, start_um=48.8)
    write_ok(policy, 0.0, policy.decide(0.0, 48.8))
    change = policy.observe(30.0, 0.0)  # an operator cleared #500
    assert change == ExternalChange(believed_um=48.8, held_um=0.0, held_cnc=0.0)
    assert (policy.applied_um, policy.external_changes) == (0.0, 1)
    assert policy.decide(30.0, 48.8).target_um == 0.0  # no budget yet: no step
    assert policy.observe(60.0, 0.0) is None  # seen once, counted once
    decision = policy.decide(60.0, 48.8)
    assert (decision.target_um, decision.write) == (10.0, True)  # 30 s at 20 µm/min
    assert policy.external_changes == 1


def test_observe_a_vacant_macro_as_zero_and_a_value_beyond_the_clamp():
    policy = CompensationPolicy(DEFAULT, start_um=12.0)
    write_ok(policy, 0.0, policy.decide(0.0, 12.0))
    change = policy.observe(10.0, math.nan)  # a CNC restarted with the macro vacant
    assert change is not None and change.held_um == 0.0 and math.isnan(change.held_cnc)
    assert policy.applied_um == 0.0
    assert policy.observe(20.0, 0.09) is not None  # 90 µm, outside the clamp
    assert policy.applied_um == 90.0  # reported as the CNC holds it
    assert policy.decide(20.0, 90.0).target_um == 50.0  # the clamp wins at once


def test_observe_recognises_a_rejected_write_that_landed():
    policy = CompensationPolicy(DEFAULT, start_um=0.0)
    write_ok(policy, 0.0, policy.decide(0.0, 0.0))
    decision = policy.decide(30.0, 20.0)
    policy.reject(30.0, "reply lost")  # the CNC did get it
    assert policy.observe(60.0, decision.value_cnc) is None
    assert (policy.applied_um, policy.external_changes) == (decision.target_um, 0)
    assert policy.decide(60.0, 20.0).write is False  # its budget restarts when it is seen
    assert policy.decide(90.0, 20.0).target_um == 20.0  # 30 s later: +10 µm


# --- misuse -----------------------------------------------------------------------------


def test_time_must_not_go_back_and_values_must_be_finite():
    with pytest.raises(ValueError, match="start_um"):
        CompensationPolicy(DEFAULT, start_um=math.nan)
    policy = CompensationPolicy(DEFAULT)
    policy.decide(10.0, 1.0)
    with pytest.raises(ValueError, match="back"):
        policy.decide(9.0, 1.0)
    with pytest.raises(ValueError, match="applied_um"):
        policy.confirm(11.0, math.inf)
    with pytest.raises(ValueError, match="back"):
        policy.reject(5.0, "late")


# --- property-style: the guarantees hold whatever happens ---------------------------------


def random_limits(rng: np.random.Generator) -> CompensationLimits:
    unit = str(rng.choice(["mm", "um"]))
    decimals = int(rng.integers(3, 6)) if unit == "mm" else int(rng.integers(0, 3))
    step_um = (1000.0 if unit == "mm" else 1.0) / 10**decimals
    ramp = None if rng.random() < 0.5 else float(rng.uniform(1.0, 120.0))
    return CompensationLimits(
        clamp_um=float(max(step_um, rng.uniform(1.0, 100.0))),
        slew_um_per_min=float(rng.uniform(1.0, 120.0)),
        deadband_um=float(rng.choice([0.0, rng.uniform(0.0, 3.0)])),
        unit=unit,  # type: ignore[arg-type]
        sign=int(rng.choice([1, -1])),  # type: ignore[arg-type]
        decimals=decimals,
        fallback_ramp_um_per_min=ramp,
        hold_on_loss_s=float(rng.choice([0.0, rng.uniform(0.0, 300.0)])),
    )


def random_prediction(rng: np.random.Generator, level_um: float) -> float | None:
    roll = rng.random()
    if roll < 0.05:
        return None
    if roll < 0.08:
        return float(rng.choice([math.nan, math.inf, -math.inf]))
    if roll < 0.12:
        return float(rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(2, 300))  # huge
    return level_um + float(rng.normal(0.0, 0.3))


@dataclass
class PolicyRun:
    """What the property test knows of the CNC between decisions."""

    limits: CompensationLimits
    now: float
    applied_since: float | None = None  # when the applied value was last set (confirm, observe)
    confirmed: tuple[float, float] | None = None  # (time, value) of the last value set
    previous_decision_s: float = 0.0
    last_usable_s: float | None = None
    writes: int = 0
    externals: int = 0

    @property
    def max_rate(self) -> float:
        return max(self.limits.slew_um_per_min, self.limits.ramp_um_per_min)


def read_back(policy: CompensationPolicy, run: PolicyRun, rng, external_rate: float) -> None:
    """The macro is read before every decision; now and then someone else wrote it."""
    limits = run.limits
    believed_um = policy.applied_um
    if rng.random() < external_rate:
        held_cnc = policy.to_cnc(float(rng.uniform(-1.2, 1.2) * limits.clamp_um))
    else:
        held_cnc = policy.to_cnc(believed_um)
    change = policy.observe(run.now, held_cnc)
    if policy.same_on_cnc(held_cnc, policy.to_cnc(believed_um)):
        assert change is None and policy.applied_um == believed_um
    else:
        assert change is not None and change.believed_um == believed_um
        assert policy.applied_um == change.held_um == policy.from_cnc(held_cnc)
        run.externals += 1
        run.applied_since, run.confirmed = run.now, (run.now, change.held_um)
    assert policy.external_changes == run.externals


def assert_decision_format(policy: CompensationPolicy, decision) -> None:
    """Never outside the clamp, before or after the CNC's rounding; written in its format."""
    limits = policy.limits
    assert abs(decision.target_um) <= limits.clamp_um + 1e-9
    assert abs(policy.from_cnc(decision.value_cnc)) <= limits.clamp_um + 1e-9
    # What is written is the target in the CNC's unit, sign and precision.
    assert decision.value_cnc == policy.to_cnc(decision.target_um)
    assert decision.value_cnc == round(decision.value_cnc, limits.decimals)
    assert decision.target_um == policy.from_cnc(decision.value_cnc)


def assert_deadband_and_slew(run: PolicyRun, decision, applied_before: float) -> None:
    """Deadband: write exactly when the change is worth it (or nothing is confirmed
    yet); a ramp to zero writes its final 0 however small. Slew: from the last applied
    value, and never more than one cycle past the deadband; rounding never carries a
    step past its budget."""
    limits = run.limits
    first = run.confirmed is None
    change_um = abs(decision.target_um - applied_before)
    zeroing = "ramping to zero" in decision.reason and decision.target_um == 0.0
    worth = change_um >= limits.deadband_um or zeroing
    assert decision.write == (first or (change_um > 0 and worth))
    if not first and abs(applied_before) <= limits.clamp_um + 1e-9:
        assert run.applied_since is not None
        banked = run.max_rate * (run.now - run.applied_since) / 60.0
        per_cycle = run.max_rate * (run.now - run.previous_decision_s) / 60.0
        assert change_um <= min(banked, limits.deadband_um + limits.step_um + per_cycle) + 1e-9


def assert_loss_handling(
    run: PolicyRun, decision, applied_before: float, usable: bool, enabled: bool
) -> None:
    """No prediction or switched off: never away from zero; within the hold, no move."""
    limits = run.limits
    if not usable or not enabled:
        assert decision.target_um * applied_before >= 0.0
        assert abs(decision.target_um) <= abs(applied_before) + limits.step_um / 2 + 1e-9
    if enabled and not usable:
        assert "no prediction" in decision.reason
        assert run.last_usable_s is not None
        holding = run.now - run.last_usable_s < limits.hold_on_loss_s
        assert ("holding" in decision.reason) == holding
        inside_clamp = abs(applied_before) <= limits.clamp_um + 1e-9
        if holding and run.confirmed is not None and inside_clamp:
            assert decision.target_um == applied_before
    if not enabled:
        assert "compensation disabled" in decision.reason


def write_outcome(
    policy: CompensationPolicy, run: PolicyRun, rng, decision, applied_before: float, fail: float
) -> None:
    """The write fails at random or is confirmed; consecutive applied values keep the slew."""
    now = run.now
    if rng.random() < fail:
        policy.reject(now, "random failure")
        assert policy.applied_um == applied_before  # a failed write never moves it
        return
    value = policy.from_cnc(decision.value_cnc)
    policy.confirm(now, value)
    if run.confirmed is not None and abs(run.confirmed[1]) <= run.limits.clamp_um + 1e-9:
        # Consecutive applied values: |Δ| <= slew · (t2 - t1) / 60.
        t1, v1 = run.confirmed
        assert abs(value - v1) <= run.max_rate * (now - t1) / 60.0 + 1e-9
    run.applied_since, run.confirmed = now, (now, value)
    run.writes += 1


@pytest.mark.parametrize("seed", range(20))
def test_guarantees_hold_for_random_predictions_failures_and_external_changes(seed):
    rng = np.random.default_rng(seed)
    limits = random_limits(rng)
    start_um = float(rng.uniform(-limits.clamp_um, limits.clamp_um))
    policy = CompensationPolicy(limits, start_um=start_um)
    failure_rate = float(rng.uniform(0.0, 0.5))
    external_rate = float(rng.uniform(0.0, 0.05))

    run = PolicyRun(limits, now=float(rng.uniform(0, 1e6)))
    run.previous_decision_s = run.now
    level_um = 0.0
    for _ in range(2000):
        run.now += float(
            rng.choice([rng.uniform(0.1, 5.0), rng.uniform(5.0, 900.0)], p=[0.95, 0.05])
        )
        if rng.random() < 0.02:
            level_um = float(rng.uniform(-1.5, 1.5) * limits.clamp_um)  # model switch, outage
        read_back(policy, run, rng, external_rate)
        run.now += float(rng.uniform(0.0, 2.0))  # the write comes a little after the read

        predicted = random_prediction(rng, level_um)
        enabled = rng.random() > 0.05
        usable = predicted is not None and math.isfinite(predicted)
        if usable or run.last_usable_s is None:
            run.last_usable_s = run.now
        applied_before = policy.applied_um
        decision = policy.decide(run.now, predicted, enabled=enabled)
        assert_decision_format(policy, decision)
        assert_deadband_and_slew(run, decision, applied_before)
        assert_loss_handling(run, decision, applied_before, usable, enabled)
        run.previous_decision_s = run.now

        if decision.write:
            write_outcome(policy, run, rng, decision, applied_before, failure_rate)
        confirmed = run.confirmed
        assert (
            abs(policy.applied_um) <= limits.clamp_um + 1e-9 or confirmed is None or run.externals
        )
    assert run.writes > 20
    assert policy.failed_writes >= 0


@pytest.mark.parametrize("seed", range(5))
def test_tracking_converges_to_a_steady_prediction(seed):
    rng = np.random.default_rng(100 + seed)
    limits = random_limits(rng)
    policy = CompensationPolicy(limits, start_um=0.0)
    goal_um = float(rng.uniform(-limits.clamp_um, limits.clamp_um))
    now = 0.0
    for _ in range(int(60 * 2 * limits.clamp_um / limits.slew_um_per_min / 3.0) + 10):
        write_ok(policy, now, policy.decide(now, goal_um))
        now += 3.0
    assert abs(policy.applied_um - goal_um) < limits.deadband_um + limits.step_um


def test_holds_applied_judges_as_observe_does() -> None:
    """The compare-before-write: the applied value within the CNC's rounding, NaN as 0."""
    policy = CompensationPolicy(DEFAULT, start_um=12.3)  # 0.0123 mm on the CNC
    assert policy.holds_applied(0.0123)
    assert policy.holds_applied(0.01234)  # within half a step of 4 decimals
    assert not policy.holds_applied(0.0124)
    assert not policy.holds_applied(0.0)  # the operator's 0
    assert not policy.holds_applied(math.nan)  # vacant: 0, not 12.3 µm
    assert CompensationPolicy(DEFAULT).holds_applied(math.nan)
    reversed_um = CompensationPolicy(CompensationLimits(unit="um", sign=-1), start_um=5.0)
    assert reversed_um.holds_applied(-5.0) and not reversed_um.holds_applied(5.0)


@pytest.mark.parametrize(
    ("limits", "held", "expected"),
    [
        (DEFAULT, 1e30, "1e+33 µm, beyond the ±50 µm clamp"),
        (DEFAULT, 1.0, "1000 µm, beyond the ±50 µm clamp"),  # 1 µm typed in mm
        (DEFAULT, -0.06, "-60 µm, beyond the ±50 µm clamp"),
        (DEFAULT, math.inf, "not a finite number"),
        (DEFAULT, 0.05, None),  # the clamp itself
        (DEFAULT, -0.0499, None),
        (DEFAULT, math.nan, None),  # vacant: read as 0
        (CompensationLimits(unit="um", sign=-1), 50.0, None),
        (CompensationLimits(unit="um", sign=-1), -51.0, "51 µm, beyond the ±50 µm clamp"),
    ],
)
def test_never_written_names_values_beyond_the_clamp(
    limits: CompensationLimits, held: float, expected: str | None
) -> None:
    assert CompensationPolicy(limits).never_written(held) == expected
