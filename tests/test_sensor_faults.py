"""simulator.faults: the offset step, the slow bias and a drift stated in °C/s."""

from __future__ import annotations

import pytest

from simulator.faults import SensorFault
from simulator.link import ChannelReading

TRUE = ChannelReading(30.0)


def test_offset_steps_and_holds_while_active() -> None:
    fault = SensorFault("T5", "offset", start_s=100.0, end_s=200.0)
    assert fault.apply(TRUE, 99.0).value_C == 30.0
    assert fault.apply(TRUE, 100.0).value_C == 33.0  # +3 °C by default
    assert fault.apply(TRUE, 199.0).value_C == 33.0
    assert fault.apply(TRUE, 200.0).value_C == 30.0


def test_bias_builds_up_over_its_ramp_then_holds() -> None:
    fault = SensorFault("T9", "bias", start_s=0.0, magnitude_C=2.0, ramp_s=7200.0)
    assert fault.apply(TRUE, 0.0).value_C == 30.0
    assert fault.apply(TRUE, 1800.0).value_C == pytest.approx(30.5)
    assert fault.apply(TRUE, 7200.0).value_C == pytest.approx(32.0)
    assert fault.apply(TRUE, 20000.0).value_C == pytest.approx(32.0)
    assert SensorFault("T9", "bias", start_s=0.0).ramp_s == 7200.0  # +2 °C over 2 h by default


def test_drift_in_degrees_per_second() -> None:
    fault = SensorFault.drift_C_per_s("T1", 0.056, start_s=10.0)
    assert fault.apply(TRUE, 40.0).value_C == pytest.approx(30.0 + 0.056 * 30.0)


def test_bad_fault_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="ramp_s applies to a 'bias' fault only"):
        SensorFault("T1", "offset", start_s=0.0, ramp_s=10.0)
    with pytest.raises(ValueError, match="ramp_s > 0"):
        SensorFault("T1", "bias", start_s=0.0, ramp_s=0.0)
