"""Tests for models.online.regime_rules: speed-regime classification and model selection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.online.regime_rules import (
    RegimeRules,
    RegimeSelector,
    Selection,
    SpeedBand,
    classify,
)

MODELS = {"variable": "mlr-error_um-spectrum", "constant": "mlr-error_um-constant"}
RULES = RegimeRules(models=MODELS)  # window 1800 s, tolerance 150 r/min, dwell 600 s


def steady(start_s: float, end_s: float, speed_rpm: float, dt_s: float = 1.0):
    """(time_s, speed_rpm) samples every dt_s in [start_s, end_s)."""
    return [(float(t), speed_rpm) for t in np.arange(start_s, end_s, dt_s)]


def spectrum(start_s: float, end_s: float, seed: int = 0, step_s: float = 120.0):
    """A variable-speed programme: a new speed every step_s, 1 s samples.

    The speeds stay at least 500 r/min away from the constant speeds the tests
    use (3000, 3500, 6000, 6500, 7500), so a segment never extends a burst.
    """
    rng = np.random.default_rng(seed)
    choices = np.array([1000.0, 2000.0, 4500.0, 5000.0, 8000.0, 9000.0])
    samples = []
    speed = 0.0
    for t in np.arange(start_s, end_s, 1.0):
        if (t - start_s) % step_s == 0:
            speed = float(rng.choice(choices[choices != speed]))
        samples.append((float(t), speed))
    return samples


def alternating(start_s: float, end_s: float, period_s: float = 5.0):
    """Speed alternating 2000 / 5000 r/min every period_s, 1 s samples."""
    return [
        (float(t), 2000.0 if int((t - start_s) // period_s) % 2 == 0 else 5000.0)
        for t in np.arange(start_s, end_s, 1.0)
    ]


def run(selector: RegimeSelector, samples) -> list[tuple[float, Selection]]:
    return [(t, selector.update(t, v)) for t, v in samples]


# --- classify ---------------------------------------------------------------------------


def test_less_than_a_window_of_history_is_variable():
    history = steady(0, 1800, 6000.0)  # last sample at 1799: window not covered at 1799
    assert classify(history, 1799.0, RULES) == "variable"
    assert classify([*history, (1800.0, 6000.0)], 1800.0, RULES) == "constant"
    assert classify([], 0.0, RULES) == "variable"


def test_constant_within_tolerance_and_variable_beyond():
    base = steady(0, 1801, 6000.0)
    within = [(t, v + (150.0 if t == 900.0 else 0.0)) for t, v in base]
    beyond = [(t, v + (150.5 if t == 900.0 else 0.0)) for t, v in base]
    assert classify(within, 1800.0, RULES) == "constant"
    assert classify(beyond, 1800.0, RULES) == "variable"


def test_only_the_window_counts():
    history = spectrum(0, 3600) + steady(3600, 5401, 6000.0)
    assert classify(history, 5399.0, RULES) == "variable"  # window starts before 3600
    assert classify(history, 5400.0, RULES) == "constant"


def test_idle_needs_a_stopped_spindle_for_the_whole_window():
    assert classify(steady(0, 1801, 0.0), 1800.0, RULES) == "idle"
    assert classify(steady(0, 1801, 0.4), 1800.0, RULES) == "idle"  # feedback jitter
    part_idle = steady(0, 900, 0.0) + steady(900, 1801, 6000.0)
    assert classify(part_idle, 1800.0, RULES) == "variable"
    # Stopped then turning slowly, within the tolerance: not constant either.
    slow = steady(0, 900, 0.0) + steady(900, 1801, 100.0)
    assert classify(slow, 1800.0, RULES) == "variable"


def test_reverse_rotation_counts_as_turning():
    assert classify(steady(0, 1801, -6000.0), 1800.0, RULES) == "constant"


def test_sample_and_hold_covers_the_window_with_irregular_samples():
    # Only two samples, an hour apart: the first holds the speed at the window start.
    history = [(0.0, 6000.0), (3600.0, 6050.0)]
    assert classify(history, 3600.0, RULES) == "constant"
    # The sample before the window start that does not hold any more is ignored.
    history = [(0.0, 1000.0), (100.0, 6000.0), (3600.0, 6050.0)]
    assert classify(history, 3600.0, RULES) == "constant"
    history = [(0.0, 1000.0), (2000.0, 6000.0), (3600.0, 6050.0)]
    assert classify(history, 3600.0, RULES) == "variable"


def test_future_samples_are_ignored():
    history = [*steady(0, 1801, 6000.0), (2000.0, 1000.0)]
    assert classify(history, 1800.0, RULES) == "constant"


BANDED = RegimeRules(
    bands=(SpeedBand("low", 0.0, 4000.0), SpeedBand("high", 4000.0, 9000.0)),
    models={"variable": "m-var", "constant/low": "m-low", "constant/high": "m-high"},
    fallback_model="m-fallback",
)


@pytest.mark.parametrize(
    ("speed_rpm", "label"),
    [(2000.0, "constant/low"), (3999.0, "constant/low"), (4000.0, "constant/high"),
     (6000.0, "constant/high"), (12000.0, "constant")],
)  # fmt: skip
def test_bands_split_constant(speed_rpm, label):
    assert classify(steady(0, 1801, speed_rpm), 1800.0, BANDED) == label


def test_band_is_chosen_by_the_middle_of_the_window_range():
    # 3900..4050 r/min: middle 3975 lies in "low" although the latest speed is "high".
    history = steady(0, 900, 3900.0) + steady(900, 1801, 4050.0)
    assert classify(history, 1800.0, BANDED) == "constant/low"


# --- model lookup -----------------------------------------------------------------------


def test_model_for_uses_own_then_parent_then_fallback():
    rules = RegimeRules(
        bands=(SpeedBand("low", 0.0, 4000.0), SpeedBand("high", 4000.0, 9000.0)),
        models={"constant/high": "m-high", "constant": "m-const"},
        fallback_model="m-fallback",
    )
    assert rules.model_for("constant/high") == "m-high"
    assert rules.model_for("constant/low") == "m-const"
    assert rules.model_for("constant") == "m-const"
    assert rules.model_for("variable") == "m-fallback"
    assert RegimeRules(models={"constant": "c"}).model_for("variable") is None


# --- selector: the programmes -----------------------------------------------------------


def test_first_update_selects_immediately():
    selection = RegimeSelector(RULES).update(0.0, 6000.0)
    assert selection.regime == "variable"
    assert selection.model_id == "mlr-error_um-spectrum"
    assert selection.switched is True
    assert "initial" in selection.reason


def test_variable_then_constant_6000_switches_exactly_once_after_the_dwell():
    selector = RegimeSelector(RULES)
    constant_from_s = 3600.0
    out = run(selector, spectrum(0, constant_from_s) + steady(constant_from_s, 9000, 6000.0))
    # Constant is seen once the whole window is 6000 (1800 s), then must hold 600 s.
    switch_s = constant_from_s + 1800.0 + 600.0
    assert selector.switches == [(switch_s, "variable", "constant")]
    switched = [t for t, s in out if s.switched]
    assert switched == [0.0, switch_s]  # the initial selection, then the one switch
    for t, s in out:
        expected = "constant" if t >= switch_s else "variable"
        assert s.regime == expected, t
        assert s.model_id == MODELS[expected]
    by_time = dict(out)
    assert "constant for 599 s of 600 s dwell: keeping variable" in by_time[switch_s - 1].reason
    assert by_time[switch_s].reason.startswith("switched from variable to constant after 600 s")


def test_short_constant_bursts_do_not_switch():
    selector = RegimeSelector(RULES)
    samples = spectrum(0, 2000, seed=1)
    t = 2000.0
    for k, speed in enumerate((6000.0, 3000.0, 6500.0, 3500.0, 7500.0)):
        # Constant for window + 500 s: classified constant for 500 s < 600 s dwell.
        samples += steady(t, t + 2300, speed)
        samples += spectrum(t + 2300, t + 2600, seed=k + 2)
        t += 2600
    out = run(selector, samples)
    assert selector.switches == []
    assert all(s.regime == "variable" and not s.switched for _, s in out[1:])
    seen = [s.reason for _, s in out if "dwell" in s.reason]
    assert len(seen) == 5 * 500  # every burst was seen as constant for 500 s
    assert all(r.startswith("constant for ") for r in seen)


def test_switch_back_to_variable_also_waits_for_the_dwell():
    selector = RegimeSelector(RULES)
    run(selector, steady(0, 2500, 6000.0))
    assert selector.switches == [(2400.0, "variable", "constant")]
    run(selector, spectrum(2500, 4000, seed=3))
    assert selector.switches == [(2400.0, "variable", "constant"), (3100.0, "constant", "variable")]


def test_idle_keeps_the_model_and_never_switches():
    # A window shorter than the dwell, so a stop is classified idle before it can switch.
    rules = RegimeRules(window_s=300.0, min_dwell_s=600.0, models=MODELS)
    selector = RegimeSelector(rules)
    run(selector, steady(0, 1000, 6000.0))
    assert selector.switches == [(900.0, "variable", "constant")]
    stop = run(selector, steady(1000, 1000 + 4 * 3600, 0.0))  # four hours stopped
    assert all(s.regime == "constant" and s.model_id == MODELS["constant"] for _, s in stop)
    assert not any(s.switched for _, s in stop)
    by_time = dict(stop)
    assert by_time[1299.0].reason.startswith("variable for 299 s")  # stopping: part idle
    assert by_time[1300.0].reason.startswith("idle: keeping constant")
    # Restart at the same speed: part idle (variable) for 300 s < dwell, then constant.
    t0 = 1000.0 + 4 * 3600
    restart = run(selector, steady(t0, t0 + 1000, 6000.0))
    assert all(s.regime == "constant" and not s.switched for _, s in restart)
    assert selector.switches == [(900.0, "variable", "constant")]


def test_a_stop_passes_through_variable_first():
    """With the default window (1800 s) longer than the dwell (600 s), a stopped
    spindle is part idle, hence variable, for 1800 s: a stop longer than the dwell
    moves the selection to variable before idle is reached, and idle keeps it."""
    selector = RegimeSelector(RULES)
    run(selector, steady(0, 2500, 6000.0))
    stop = run(selector, steady(2500, 2500 + 3600, 0.0))
    assert selector.switches == [(2400.0, "variable", "constant"), (3100.0, "constant", "variable")]
    assert dict(stop)[6099.0].reason.startswith("idle: keeping variable")


def test_idle_interrupts_the_dwell_of_a_candidate():
    rules = RegimeRules(window_s=20.0, min_dwell_s=50.0, models=MODELS)
    selector = RegimeSelector(rules)
    run(selector, steady(0, 71, 3000.0))  # constant from 20, switch at 70
    assert selector.switches == [(70.0, "variable", "constant")]
    # Variable from 71 to 110 (candidate for 39 s), idle from 111, variable again at 200.
    run(selector, alternating(71, 91))
    out = run(selector, steady(91, 200, 0.0))
    assert dict(out)[110.0].reason.startswith("variable for 39 s of 50 s dwell")
    assert dict(out)[111.0].reason.startswith("idle: keeping constant")
    out = run(selector, alternating(200, 240))
    assert selector.switches == [(70.0, "variable", "constant")]
    assert all(s.regime == "constant" for _, s in out)
    assert out[-1][1].reason.startswith("variable for 39 s of 50 s dwell")
    # Without the idle reset the candidate would have been "held" since 71.
    assert selector.update(250.0, 2000.0).switched is True


def test_zero_dwell_switches_as_soon_as_classified():
    rules = RegimeRules(min_dwell_s=0.0, models=MODELS)
    selector = RegimeSelector(rules)
    run(selector, steady(0, 1801, 6000.0))
    assert selector.switches == [(1800.0, "variable", "constant")]


def test_bands_with_their_own_models():
    selector = RegimeSelector(BANDED)
    run(selector, steady(0, 2400, 2000.0))
    selection = selector.update(2400.0, 2000.0)
    assert (selection.regime, selection.model_id, selection.switched) == (
        "constant/low",
        "m-low",
        True,
    )
    run(selector, steady(2401, 4801, 7000.0))
    selection = selector.update(4801.0, 7000.0)
    assert (selection.regime, selection.model_id) == ("constant/high", "m-high")
    # Outside every band: plain "constant", which has no model here -> fallback.
    run(selector, steady(4802, 7202, 12000.0))
    selection = selector.update(7202.0, 12000.0)
    assert selection.regime == "constant"
    assert selection.model_id == "m-fallback"
    assert "no own model for constant, using m-fallback" in selection.reason
    assert selector.switches == [
        (2400.0, "variable", "constant/low"),
        (3001.0, "constant/low", "variable"),  # the change of speed, held for the dwell
        (4801.0, "variable", "constant/high"),
        (5402.0, "constant/high", "variable"),
        (7202.0, "variable", "constant"),
    ]


def test_no_model_and_no_fallback_gives_none():
    selector = RegimeSelector(RegimeRules(models={"constant": "m-const"}))
    selection = selector.update(0.0, 1000.0)
    assert selection.model_id is None
    assert "no model for variable" in selection.reason


def test_jittered_cycle_times_still_reach_constant():
    """Cycle times never land on now - window_s: the held sample must cover the gap."""
    rng = np.random.default_rng(7)
    rules = RegimeRules(window_s=300.0, min_dwell_s=60.0, models=MODELS)
    selector = RegimeSelector(rules)
    t = 0.0
    while t < 600.0:
        selector.update(t, 6000.0 + float(rng.uniform(-20, 20)))
        t += float(rng.uniform(0.5, 1.5))
    assert len(selector.switches) == 1
    switch_s = selector.switches[0][0]
    assert 360.0 <= switch_s < 363.0


def test_history_is_bounded_by_the_window():
    rules = RegimeRules(window_s=100.0, min_dwell_s=0.0)
    selector = RegimeSelector(rules)
    for t in range(5000):
        selector.update(float(t), 1000.0 + (t % 3))
    assert len(selector._history) <= 102  # the window plus the held sample


def run_start(seen: list[tuple[float, str]]) -> float:
    """When the latest label started its current unbroken run."""
    start_s = seen[-1][0]
    for t_past, label in reversed(seen):
        if label != seen[-1][1]:
            break
        start_s = t_past
    return start_s


@pytest.mark.parametrize("seed", range(4))
def test_random_programmes_respect_the_dwell(seed):
    """Property: the selection only changes after min_dwell_s of one regime, never to idle."""
    rng = np.random.default_rng(seed)
    rules = RegimeRules(window_s=200.0, min_dwell_s=80.0, constant_tolerance_rpm=100.0)
    selector = RegimeSelector(rules)
    history: list[tuple[float, float]] = []
    seen: list[tuple[float, str]] = []
    t = 0.0
    selected = None
    while t < 20000.0:
        end_s = t + float(rng.uniform(10, 600))
        kind = rng.choice(["stop", "constant", "spectrum"])
        speed = float(rng.uniform(500, 9000))
        while t < end_s:
            if kind == "stop":
                value = 0.0
            elif kind == "constant":
                value = speed + float(rng.uniform(-30, 30))
            else:
                value = float(rng.uniform(500, 9000))
            history.append((t, value))
            seen.append((t, classify(history[-500:], t, rules)))
            selection = selector.update(t, value)
            assert selection.regime != "idle"
            assert selection.switched == (selection.regime != selected)
            label = seen[-1][1]
            held_s = t - run_start(seen)
            if selected is not None and label not in ("idle", selected):
                # Switch exactly when the new regime has been seen without a break for the dwell.
                assert selection.switched == (held_s >= rules.min_dwell_s), (t, held_s)
            else:
                assert not selection.switched or selected is None
            selected = selection.regime
            t += float(rng.uniform(0.5, 5.0))
    assert len(selector.switches) > 5  # the property was exercised


# --- invalid rules ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"window_s": 0.0}, "window_s"),
        ({"window_s": -5.0}, "window_s"),
        ({"window_s": math.nan}, "window_s"),
        ({"min_dwell_s": -1.0}, "min_dwell_s"),
        ({"constant_tolerance_rpm": -1.0}, "constant_tolerance_rpm"),
        ({"bands": (SpeedBand("a", 100.0, 100.0),)}, "bands"),
        ({"bands": (SpeedBand("a", 5000.0, 1000.0),)}, "bands"),
        ({"bands": (SpeedBand("a", 0.0, 5000.0), SpeedBand("b", 4000.0, 9000.0))}, "overlaps"),
        ({"bands": (SpeedBand("a", 0.0, 1.0), SpeedBand("a", 2.0, 3.0))}, "duplicate"),
        ({"bands": (SpeedBand("", 0.0, 1.0),)}, "bands"),
        ({"models": {"constnat": "x"}}, "models"),
        ({"models": {"constant/high": "x"}}, "models"),  # no band "high"
        ({"models": {"idle": "x"}}, "models"),  # idle never selects a model
    ],
)
def test_invalid_rules_raise_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        RegimeRules(**kwargs)


def test_adjacent_bands_are_not_overlapping():
    rules = RegimeRules(bands=(SpeedBand("b", 4000.0, 9000.0), SpeedBand("a", 0.0, 4000.0)))
    assert len(rules.bands) == 2


def test_rules_are_immutable():
    models = dict(MODELS)
    rules = RegimeRules(models=models)
    models["variable"] = "changed later"
    assert rules.models["variable"] == "mlr-error_um-spectrum"
    with pytest.raises(TypeError):
        rules.models["variable"] = "x"  # type: ignore[index]


def test_selector_rejects_time_going_back_and_non_finite_speed():
    selector = RegimeSelector(RULES)
    selector.update(10.0, 1000.0)
    with pytest.raises(ValueError, match="back"):
        selector.update(9.0, 1000.0)
    with pytest.raises(ValueError, match="finite"):
        selector.update(11.0, math.nan)
