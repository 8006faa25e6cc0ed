"""Tests for gateway.live.quality: per-sensor quality flags with recovery hysteresis."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from gateway.limits import QualityLimits
from gateway.live.quality import Quality, QualityMonitor, SensorCheck

GOOD = Quality.GOOD
BAD = Quality.BAD


def ok(value_C: float | None) -> tuple[float | None, int | None]:
    """A reading with transmitter status OK."""
    return (value_C, 0)


def trusted_monitor(
    sensors: dict[str, float], limits: QualityLimits | None = None, start_s: float = 0.0
) -> tuple[QualityMonitor, float]:
    """A monitor whose sensors have passed their start-up recovery; returns (monitor, now_s)."""
    lim = limits or QualityLimits()
    monitor = QualityMonitor(list(sensors), lim)
    now_s = start_s
    for _ in range(lim.recover_cycles):
        monitor.check(now_s, {s: ok(v) for s, v in sensors.items()})
        now_s += 1.0
    checks = monitor.check(now_s, {s: ok(v) for s, v in sensors.items()})
    assert all(c.quality is GOOD for c in checks.values()), checks
    return monitor, now_s


# --- start-up and plain good values -----------------------------------------------------


def test_a_new_sensor_is_trusted_after_recover_cycles_good_checks():
    monitor = QualityMonitor(["T1"], QualityLimits())
    assert monitor.check(0.0, {"T1": (None, None)})["T1"] == SensorCheck("T1", BAD, "no value yet")
    assert monitor.last_good("T1") is None
    got = [monitor.check(t, {"T1": ok(25.0 + 0.01 * t)})["T1"] for t in (1.0, 2.0, 3.0, 4.0)]
    assert [(c.quality, c.reason) for c in got] == [
        (BAD, "recovering (1/3 good)"),
        (BAD, "recovering (2/3 good)"),
        (GOOD, None),
        (GOOD, None),
    ]
    assert monitor.last_good("T1") == pytest.approx(25.04)


def test_recover_cycles_zero_trusts_the_first_good_value():
    monitor = QualityMonitor(["T1"], QualityLimits(recover_cycles=0))
    assert monitor.check(0.0, {"T1": ok(25.0)})["T1"] == SensorCheck("T1", GOOD, None)
    assert monitor.check(1.0, {"T1": ok(200.0)})["T1"].quality is BAD
    assert monitor.check(2.0, {"T1": ok(25.0)})["T1"].quality is GOOD


def test_check_returns_every_sensor_in_order():
    monitor = QualityMonitor(["T3", "T1", "T2"], QualityLimits())
    checks = monitor.check(0.0, {"T1": ok(20.0)})
    assert list(checks) == ["T3", "T1", "T2"]
    assert all(checks[s].sensor == s for s in checks)


def test_status_none_means_no_status_information():
    monitor, now = trusted_monitor({"T1": 25.0})
    assert monitor.check(now + 1, {"T1": (25.0, None)})["T1"].quality is GOOD


# --- transmitter faults -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("status", "reason"),
    [
        (1, "transmitter fault code 1 (open circuit)"),
        (2, "transmitter fault code 2 (short circuit)"),
        (3, "transmitter fault code 3 (out of range)"),
        (7, "transmitter fault code 7"),
    ],
)
def test_transmitter_fault_is_bad_whatever_the_value(status, reason):
    monitor, now = trusted_monitor({"T1": 25.0})
    # An open Pt100 often still delivers a plausible-looking number: the status wins.
    check = monitor.check(now + 1, {"T1": (25.0, status)})["T1"]
    assert check == SensorCheck("T1", BAD, reason)
    assert monitor.check(now + 2, {"T1": (None, status)})["T1"].reason == reason


def test_open_circuit_then_recovery_needs_three_good_checks():
    monitor, now = trusted_monitor({"T1": 25.0})
    assert monitor.check(now + 1, {"T1": (850.0, 1)})["T1"].quality is BAD
    assert monitor.last_good("T1") == 25.0
    reasons = [monitor.check(now + 1 + k, {"T1": ok(25.0)})["T1"].reason for k in (1, 2, 3)]
    assert reasons == ["recovering (1/3 good)", "recovering (2/3 good)", None]


# --- range ------------------------------------------------------------------------------


def test_out_of_range_high_and_low():
    limits = QualityLimits(recover_cycles=0)
    monitor = QualityMonitor(["T1"], limits)
    assert monitor.check(0.0, {"T1": ok(150.3)})["T1"] == SensorCheck(
        "T1", BAD, "out of range: 150.3 °C > 120.0 °C"
    )
    assert monitor.check(1.0, {"T1": ok(-25.0)})["T1"] == SensorCheck(
        "T1", BAD, "out of range: -25.0 °C < -20.0 °C"
    )
    assert monitor.last_good("T1") is None


def test_range_limits_are_inclusive():
    limits = QualityLimits(min_C=10.0, max_C=30.0, recover_cycles=0, max_rate_C_per_s=100.0)
    monitor = QualityMonitor(["T1"], limits)
    assert monitor.check(0.0, {"T1": ok(30.0)})["T1"].quality is GOOD
    assert monitor.check(1.0, {"T1": ok(10.0)})["T1"].quality is GOOD
    assert monitor.check(2.0, {"T1": ok(30.01)})["T1"].quality is BAD


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_value_is_bad(value):
    monitor, now = trusted_monitor({"T1": 25.0})
    check = monitor.check(now + 1, {"T1": ok(value)})["T1"]
    assert check.quality is BAD
    assert "not a finite value" in check.reason
    assert monitor.last_good("T1") == 25.0


def test_per_sensor_limits():
    limits = {
        "spindle": QualityLimits(max_C=80.0, recover_cycles=0),
        "ambient": QualityLimits(max_C=45.0, recover_cycles=0),
    }
    monitor = QualityMonitor(["spindle", "ambient"], limits)
    checks = monitor.check(0.0, {"spindle": ok(50.0), "ambient": ok(50.0)})
    assert checks["spindle"].quality is GOOD
    assert checks["ambient"].reason == "out of range: 50.0 °C > 45.0 °C"


# --- rate / spikes ----------------------------------------------------------------------


def test_spike_is_bad_and_the_next_sample_is_judged_against_the_pre_spike_value():
    monitor, now = trusted_monitor({"T1": 25.0})
    spike = monitor.check(now + 1, {"T1": ok(28.1)})["T1"]
    assert spike == SensorCheck("T1", BAD, "rate 3.10 °C/s > 0.5 °C/s")
    assert monitor.last_good("T1") == 25.0
    # 25.6 is 2.5 °C/s away from the spike but only 0.3 °C/s from 25.0 two seconds ago.
    after = monitor.check(now + 2, {"T1": ok(25.6)})["T1"]
    assert after == SensorCheck("T1", BAD, "recovering (1/3 good)")
    assert monitor.last_good("T1") == 25.6
    assert monitor.check(now + 3, {"T1": ok(25.6)})["T1"].reason == "recovering (2/3 good)"
    assert monitor.check(now + 4, {"T1": ok(25.6)})["T1"] == SensorCheck("T1", GOOD, None)


def test_a_sample_returning_to_the_spike_level_is_still_a_spike():
    monitor, now = trusted_monitor({"T1": 25.0})
    monitor.check(now + 1, {"T1": ok(28.1)})
    # Close to the spike, but 1.55 °C/s from the last good value: still bad.
    check = monitor.check(now + 2, {"T1": ok(28.1)})["T1"]
    assert check == SensorCheck("T1", BAD, "rate 1.55 °C/s > 0.5 °C/s")


def test_rate_exactly_at_the_limit_is_good():
    monitor, now = trusted_monitor({"T1": 25.0})
    assert monitor.check(now + 2, {"T1": ok(26.0)})["T1"].quality is GOOD


def test_a_real_step_recovers_once_the_rate_since_the_last_good_value_is_plausible():
    """A sensor replaced by a warmer one is not bad forever: the allowed change grows."""
    monitor, now = trusted_monitor({"T1": 25.0})
    t0 = now
    qualities = {}
    for k in range(1, 40):
        qualities[k] = monitor.check(t0 + k, {"T1": ok(35.0)})["T1"]
    assert all(qualities[k].reason.startswith("rate") for k in range(1, 20))
    assert qualities[20].reason == "recovering (1/3 good)"  # 10 °C / 20 s = 0.5 °C/s
    assert qualities[22] == SensorCheck("T1", GOOD, None)
    assert monitor.last_good("T1") == 35.0


# --- hysteresis -------------------------------------------------------------------------


def test_flickering_sensor_never_flaps_to_good():
    monitor, now = trusted_monitor({"T1": 25.0})
    for k in range(1, 41):
        value = 25.0 if k % 3 else 200.0  # good, good, bad, good, good, bad, ...
        check = monitor.check(now + k, {"T1": ok(value)})["T1"]
        if k >= 3:
            assert check.quality is BAD, (k, check)


def test_a_bad_check_during_recovery_restarts_the_count():
    monitor, now = trusted_monitor({"T1": 25.0})
    monitor.check(now + 1, {"T1": (None, 2)})
    assert monitor.check(now + 2, {"T1": ok(25.0)})["T1"].reason == "recovering (1/3 good)"
    assert monitor.check(now + 3, {"T1": ok(25.0)})["T1"].reason == "recovering (2/3 good)"
    assert monitor.check(now + 4, {"T1": ok(999.0)})["T1"].reason.startswith("out of range")
    assert monitor.check(now + 5, {"T1": ok(25.0)})["T1"].reason == "recovering (1/3 good)"


# --- missed reads and stale -------------------------------------------------------------


def test_single_missed_read_keeps_quality_and_is_not_a_new_value():
    monitor, now = trusted_monitor({"T1": 25.0})
    assert monitor.check(now + 1, {"T1": (None, None)})["T1"] == SensorCheck("T1", GOOD, None)
    assert monitor.check(now + 2, {})["T1"] == SensorCheck("T1", GOOD, None)  # missing key
    assert monitor.last_good("T1") == 25.0
    # The next value is judged against 25.0 three seconds ago: 1.2 °C is 0.4 °C/s.
    assert monitor.check(now + 3, {"T1": ok(26.2)})["T1"].quality is GOOD


def test_missed_read_during_recovery_does_not_count_as_a_good_check():
    monitor, now = trusted_monitor({"T1": 25.0})
    monitor.check(now + 1, {"T1": (None, 1)})
    assert monitor.check(now + 2, {"T1": ok(25.0)})["T1"].reason == "recovering (1/3 good)"
    assert monitor.check(now + 3, {"T1": (None, None)})["T1"].reason == "recovering (1/3 good)"
    assert monitor.check(now + 4, {"T1": ok(25.0)})["T1"].reason == "recovering (2/3 good)"
    assert monitor.check(now + 5, {"T1": ok(25.0)})["T1"].quality is GOOD


def test_stale_after_stale_s_without_a_value_then_recovery():
    monitor, now = trusted_monitor({"T1": 25.0})
    last_good_s = now
    checks = {k: monitor.check(last_good_s + k, {"T1": (None, None)})["T1"] for k in range(1, 13)}
    assert all(checks[k].quality is GOOD for k in range(1, 11))  # 10 s is not yet stale
    assert checks[11] == SensorCheck("T1", BAD, "stale: no value for 11.0 s")
    assert checks[12] == SensorCheck("T1", BAD, "stale: no value for 12.0 s")
    assert monitor.last_good("T1") == 25.0
    back = [monitor.check(last_good_s + k, {"T1": ok(25.0)})["T1"] for k in (13, 14, 15)]
    assert [c.quality for c in back] == [BAD, BAD, GOOD]
    assert back[0].reason == "recovering (1/3 good)"


def test_a_sensor_that_never_answers_goes_stale():
    monitor = QualityMonitor(["T1"], QualityLimits(stale_s=5.0))
    assert monitor.check(100.0, {})["T1"].reason == "no value yet"
    assert monitor.check(105.0, {})["T1"].reason == "no value yet"
    assert monitor.check(105.5, {})["T1"].reason == "stale: no value for 5.5 s"


# --- stuck ------------------------------------------------------------------------------


def run_heating(
    monitor, start_s, seconds, stuck_C, heating_C_per_s=0.01, wobble_C=0.0, heat_from_C=30.0
):
    """T_stuck holds its value (± wobble) while T_heat rises; returns {k: checks}."""
    out = {}
    for k in range(1, seconds + 1):
        stuck = stuck_C + (wobble_C if k % 2 else 0.0)
        heat = heat_from_C + heating_C_per_s * k
        out[k] = monitor.check(start_s + k, {"T_stuck": ok(stuck), "T_heat": ok(heat)})
    return out


def test_stuck_while_another_sensor_heats():
    monitor, now = trusted_monitor({"T_stuck": 25.3, "T_heat": 30.0})
    # T_stuck has held 25.3 since start-up (now - 3 s), T_heat starts heating.
    since_s = now - 3
    out = run_heating(monitor, now, 920, 25.3)
    first_bad = min(k for k, c in out.items() if c["T_stuck"].quality is BAD)
    assert now + first_bad - since_s == 900  # held for stuck_s exactly
    assert all(out[k]["T_stuck"].quality is BAD for k in range(first_bad, 921))
    assert out[909]["T_stuck"].reason == "stuck at 25.3 °C for 912 s"
    assert all(c["T_heat"].quality is GOOD for c in out.values())


def test_constant_value_on_a_cold_machine_is_not_stuck():
    monitor, now = trusted_monitor({"T_stuck": 25.3, "T_heat": 30.0})
    # The other sensor moves by 0.9 °C in 3000 s: the machine is not heating.
    out = run_heating(monitor, now, 3000, 25.3, heating_C_per_s=0.0003)
    assert all(c["T_stuck"].quality is GOOD for c in out.values())


def test_stuck_sensor_that_moves_again_recovers():
    monitor, now = trusted_monitor({"T_stuck": 25.3, "T_heat": 30.0})
    run_heating(monitor, now, 1000, 25.3)
    t = now + 1000
    got = [
        monitor.check(t + k, {"T_stuck": ok(25.3 + 0.1 * k), "T_heat": ok(40.0 + 0.01 * k)})
        for k in (1, 2, 3)
    ]
    assert [c["T_stuck"].quality for c in got] == [BAD, BAD, GOOD]
    assert got[0]["T_stuck"].reason == "recovering (1/3 good)"
    assert monitor.last_good("T_stuck") == pytest.approx(25.6)


def test_stuck_sensor_stays_bad_after_the_others_settle():
    monitor, now = trusted_monitor({"T_stuck": 25.3, "T_heat": 30.0})
    out = run_heating(monitor, now, 1000, 25.3)  # found stuck after 900 s
    assert out[1000]["T_stuck"].quality is BAD
    # The machine then sits still for an hour: nothing moves, the reading is still frozen.
    t = now + 1000
    later = [
        monitor.check(t + k, {"T_stuck": ok(25.3), "T_heat": ok(40.0)}) for k in range(1, 3601)
    ]
    assert all(c["T_stuck"].quality is BAD for c in later)
    assert later[-1]["T_stuck"].reason.startswith("stuck at 25.3 °C for ")


def test_stuck_band_tolerates_a_last_digit_wobble():
    limits = QualityLimits(stuck_band_C=0.1)
    monitor, now = trusted_monitor({"T_stuck": 25.3, "T_heat": 30.0}, limits)
    out = run_heating(monitor, now, 950, 25.3, wobble_C=0.05)
    assert out[950]["T_stuck"].reason.startswith("stuck at")
    # With the default band of 0.0 the same wobble is movement.
    monitor, now = trusted_monitor({"T_stuck": 25.3, "T_heat": 30.0})
    out = run_heating(monitor, now, 950, 25.3, wobble_C=0.05)
    assert all(c["T_stuck"].quality is GOOD for c in out.values())


def test_bad_samples_break_a_constant_run():
    monitor, now = trusted_monitor({"T_stuck": 25.3, "T_heat": 30.0})
    run_heating(monitor, now, 500, 25.3)
    t = now + 500
    monitor.check(t + 1, {"T_stuck": (25.3, 1), "T_heat": ok(35.01)})
    out = run_heating(monitor, t + 1, 800, 25.3, heat_from_C=35.01)
    assert all(c["T_heat"].quality is GOOD for c in out.values())
    # Without the fault T_stuck would have held 25.3 for 1300 s by now.
    assert all(c["T_stuck"].quality is GOOD for k, c in out.items() if k > 3)


# --- property-style: the flag never trusts what it must not ------------------------------


def random_reading(rng: np.random.Generator, true_C: float) -> tuple[float | None, int | None]:
    """A reading of a sensor at ``true_C``: mostly right, sometimes wild, faulty or missed."""
    roll = rng.random()
    if roll < 0.05:
        return (float(rng.uniform(-100, 900)), 0)  # wild value
    if roll < 0.08:
        return (float(rng.choice([math.nan, math.inf])), 0)
    if roll < 0.12:
        return (true_C, int(rng.integers(1, 4)))  # fault
    if roll < 0.25:
        return (None, None)  # missed
    return (true_C, 0)


@dataclass
class SensorTrack:
    """What the property test remembers of one sensor between cycles."""

    streak: int = 0  # consecutive passing checks with a value
    last_good_s: float | None = None
    previous: SensorCheck | None = None


def assert_verdict_sound(
    monitor: QualityMonitor,
    limits: QualityLimits,
    now: float,
    reading: tuple[float | None, int | None],
    check: SensorCheck,
    track: SensorTrack,
) -> None:
    """One sensor's verdict of one cycle is consistent with its reading and its history."""
    value, status = reading
    assert (check.reason is None) == (check.quality is GOOD)
    if value is None and status in (None, 0):
        if track.last_good_s is not None and now - track.last_good_s <= limits.stale_s:
            assert check == track.previous
        if check.reason and check.reason.startswith("stale"):
            track.streak = 0
        return
    passing = check.quality is GOOD or check.reason.startswith("recovering")
    track.streak = track.streak + 1 if passing else 0
    if check.quality is GOOD:
        assert status == 0
        assert limits.min_C <= value <= limits.max_C
        was_good = track.previous is not None and track.previous.quality is GOOD
        assert was_good or track.streak >= limits.recover_cycles
    if passing:
        assert monitor.last_good(check.sensor) == value
        track.last_good_s = now


@pytest.mark.parametrize("seed", range(6))
def test_random_readings_never_yield_an_implausible_good(seed):
    rng = np.random.default_rng(seed)
    limits = QualityLimits(
        min_C=-20.0,
        max_C=120.0,
        max_rate_C_per_s=float(rng.uniform(0.2, 2.0)),
        stale_s=float(rng.uniform(2.0, 20.0)),
        recover_cycles=int(rng.integers(0, 5)),
    )
    sensors = ["T1", "T2", "T3"]
    monitor = QualityMonitor(sensors, limits)
    true_C = {s: 25.0 for s in sensors}
    tracks = {s: SensorTrack() for s in sensors}
    now = 0.0
    for _ in range(3000):
        now += float(rng.uniform(0.2, 3.0))
        readings = {}
        for s in sensors:
            true_C[s] += float(rng.normal(0.0, 0.05))
            readings[s] = random_reading(rng, true_C[s])
        checks = monitor.check(now, readings)
        for s in sensors:
            assert checks[s].sensor == s
            assert_verdict_sound(monitor, limits, now, readings[s], checks[s], tracks[s])
        for s in sensors:
            tracks[s].previous = checks[s]
            good = monitor.last_good(s)
            assert good is None or (math.isfinite(good) and -20.0 <= good <= 120.0)


# --- configuration errors ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"min_C": 50.0, "max_C": 40.0}, "min_C"),
        ({"max_rate_C_per_s": 0.0}, "max_rate_C_per_s"),
        ({"stuck_s": -1.0}, "stuck_s"),
        ({"stuck_band_C": -0.1}, "stuck_band_C"),
        ({"stale_s": 0.0}, "stale_s"),
        ({"recover_cycles": -1}, "recover_cycles"),
        ({"max_C": math.nan}, "max_C"),
    ],
)
def test_invalid_limits_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        QualityLimits(**kwargs)


def test_monitor_rejects_bad_setup_and_calls():
    with pytest.raises(ValueError, match="empty"):
        QualityMonitor([], QualityLimits())
    with pytest.raises(ValueError, match="unique"):
        QualityMonitor(["T1", "T1"], QualityLimits())
    with pytest.raises(ValueError, match="missing"):
        QualityMonitor(["T1", "T2"], {"T1": QualityLimits()})
    monitor = QualityMonitor(["T1"], QualityLimits())
    with pytest.raises(ValueError, match="unknown"):
        monitor.check(0.0, {"T9": ok(20.0)})
    monitor.check(1.0, {"T1": ok(20.0)})
    with pytest.raises(ValueError, match="increase"):
        monitor.check(1.0, {"T1": ok(20.0)})
    with pytest.raises(KeyError):
        monitor.last_good("T9")
