"""The limits the owner of a machine sets: one definition of each, with its default.

The configuration's sections (:mod:`gateway.config`) take their defaults from here
and build these objects; the live loop (:mod:`gateway.live`) only reads them. So a
default is written once, and a limit the loop receives has been checked once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Literal

#: µm in one unit of the CNC's macro variable.
UM_PER_UNIT = {"mm": 1000.0, "um": 1.0}


@dataclass(frozen=True)
class CompensationLimits:
    """Limits and CNC format of the compensation value of one axis.

    Attributes:
        clamp_um: largest magnitude ever written (µm, > 0).
        slew_um_per_min: fastest change of the written value (µm/min, > 0).
        deadband_um: smaller changes are not written (µm, >= 0).
        unit: unit of the CNC macro variable.
        sign: +1 or -1, the CNC's sign convention relative to the predicted error.
        decimals: digits after the point the CNC keeps, in its unit; every
            written value is rounded to them.
        fallback_ramp_um_per_min: rate of the ramp to zero when there is no
            prediction (None: ``slew_um_per_min``).
        hold_on_loss_s: how long the applied value is held after the last cycle
            with a prediction before the ramp to zero starts (s, >= 0).
    """

    clamp_um: float = 50.0
    slew_um_per_min: float = 20.0
    deadband_um: float = 0.5
    unit: Literal["mm", "um"] = "mm"
    sign: Literal[1, -1] = 1
    decimals: int = 4
    fallback_ramp_um_per_min: float | None = None
    hold_on_loss_s: float = 60.0

    def __post_init__(self) -> None:
        self._check_format()
        self._check_magnitudes()

    def _check_format(self) -> None:
        """The CNC side: unit, sign convention and decimals of the macro variable."""
        if self.unit not in UM_PER_UNIT:
            raise ValueError(f"CompensationLimits.unit must be 'mm' or 'um', got {self.unit!r}")
        if self.sign not in (1, -1) or isinstance(self.sign, bool):
            raise ValueError(f"CompensationLimits.sign must be 1 or -1, got {self.sign!r}")
        if not isinstance(self.decimals, int) or isinstance(self.decimals, bool):
            raise ValueError(f"CompensationLimits.decimals must be an int, got {self.decimals!r}")
        if not 0 <= self.decimals <= 9:
            raise ValueError(f"CompensationLimits.decimals must be in 0..9, got {self.decimals}")

    def _check_magnitudes(self) -> None:
        """The owner's limits: clamp, slew, deadband, fallback ramp and hold time."""
        if not (math.isfinite(self.clamp_um) and self.clamp_um > 0):
            raise ValueError(
                f"CompensationLimits.clamp_um must be > 0 (0 would forbid any compensation), "
                f"got {self.clamp_um}"
            )
        if self.clamp_um < self.step_um:
            raise ValueError(
                f"CompensationLimits.clamp_um ({self.clamp_um}) is below one CNC step "
                f"({self.step_um} µm at {self.decimals} decimals in {self.unit})"
            )
        if not (math.isfinite(self.slew_um_per_min) and self.slew_um_per_min > 0):
            raise ValueError(
                f"CompensationLimits.slew_um_per_min must be > 0, got {self.slew_um_per_min}"
            )
        if not (math.isfinite(self.deadband_um) and self.deadband_um >= 0):
            raise ValueError(f"CompensationLimits.deadband_um must be >= 0, got {self.deadband_um}")
        ramp = self.fallback_ramp_um_per_min
        if ramp is not None and not (math.isfinite(ramp) and ramp > 0):
            raise ValueError(
                f"CompensationLimits.fallback_ramp_um_per_min must be > 0 or None, got {ramp}"
            )
        if not (math.isfinite(self.hold_on_loss_s) and self.hold_on_loss_s >= 0):
            raise ValueError(
                f"CompensationLimits.hold_on_loss_s must be >= 0 and finite, "
                f"got {self.hold_on_loss_s}"
            )

    @property
    def step_um(self) -> float:
        """One step of the CNC's precision, in µm."""
        return UM_PER_UNIT[self.unit] / 10**self.decimals

    @property
    def ramp_um_per_min(self) -> float:
        """Rate of the ramp to zero when there is no prediction."""
        ramp = self.fallback_ramp_um_per_min
        return self.slew_um_per_min if ramp is None else ramp


@dataclass(frozen=True)
class QualityLimits:
    """Limits of one sensor.

    Attributes:
        min_C, max_C: plausible range; outside it the value is BAD.
        max_rate_C_per_s: fastest believable change since the last good value.
        stuck_s: how long a value may stay within ``stuck_band_C`` while another
            sensor moves by more than 1 °C before it is declared stuck.
        stuck_band_C: a change no larger than this counts as "not moving"
            (0.0: exactly the same value).
        stale_s: how long a sensor may deliver no value before it is BAD.
        recover_cycles: consecutive good checks needed after a BAD one before
            the sensor is trusted (GOOD) again.
    """

    min_C: float = -20.0
    max_C: float = 120.0
    max_rate_C_per_s: float = 0.5
    stuck_s: float = 900.0
    stuck_band_C: float = 0.0
    stale_s: float = 10.0
    recover_cycles: int = 3

    def __post_init__(self) -> None:
        for f in fields(self):
            if not math.isfinite(getattr(self, f.name)):
                raise ValueError(
                    f"QualityLimits.{f.name} must be finite, got {getattr(self, f.name)}"
                )
        if self.min_C >= self.max_C:
            raise ValueError(f"QualityLimits.min_C ({self.min_C}) must be < max_C ({self.max_C})")
        if self.max_rate_C_per_s <= 0:
            raise ValueError(
                f"QualityLimits.max_rate_C_per_s must be > 0, got {self.max_rate_C_per_s}"
            )
        if self.stuck_s <= 0:
            raise ValueError(f"QualityLimits.stuck_s must be > 0, got {self.stuck_s}")
        if self.stuck_band_C < 0:
            raise ValueError(f"QualityLimits.stuck_band_C must be >= 0, got {self.stuck_band_C}")
        if self.stale_s <= 0:
            raise ValueError(f"QualityLimits.stale_s must be > 0, got {self.stale_s}")
        if not isinstance(self.recover_cycles, int) or self.recover_cycles < 0:
            raise ValueError(
                f"QualityLimits.recover_cycles must be an int >= 0, got {self.recover_cycles!r}"
            )


@dataclass(frozen=True)
class PlausibilityLimits:
    """Thresholds of both rules (see the module docstring).

    Attributes:
        sigma: a sensor further than this many σ from what the others say is suspect.
        min_sigma_C: floor of the σ a residual is divided by, °C (the
            transmitters' 0.1 °C register step, and a fast sensor leading the
            others by a few tenths through a speed step: a relation fitted
            tightly must not turn that into a fault).
        recover_s: how long a held sensor must agree again before it is trusted, s.
        max_prediction_rate_um_per_s: fastest believable change of the predicted error.
        prediction_noise_um: change allowed on top of the rate (sensor noise
            times the model's coefficients, register steps).
    """

    sigma: float = 5.0
    min_sigma_C: float = 0.1
    recover_s: float = 900.0
    max_prediction_rate_um_per_s: float = 0.1
    prediction_noise_um: float = 1.0

    def __post_init__(self) -> None:
        for name in ("sigma", "min_sigma_C", "max_prediction_rate_um_per_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"PlausibilityLimits.{name} must be finite and > 0, got {value}")
        for name in ("recover_s", "prediction_noise_um"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"PlausibilityLimits.{name} must be finite and ≥ 0, got {value}")


@dataclass(frozen=True, kw_only=True)
class LoginLimits:
    """When a login key is locked, and for how long (:mod:`gateway.scada.login_throttle`):
    the SCADA server's and the console's ``login_*`` settings."""

    max_failures: int = 5
    window_s: float = 60.0
    lockout_s: float = 30.0
    max_lockout_s: float = 900.0
    forget_s: float = 3600.0

    def __post_init__(self) -> None:
        if self.max_failures < 1:
            raise ValueError(f"max_failures must be at least 1, got {self.max_failures}")
        if not 0 < self.lockout_s <= self.max_lockout_s:
            raise ValueError(
                f"need 0 < lockout_s ({self.lockout_s}) <= max_lockout_s ({self.max_lockout_s})"
            )
        if self.window_s <= 0 or self.forget_s <= 0:
            raise ValueError("window_s and forget_s must be positive")

    def lockout_for(self, previous_lockouts: int) -> float:
        """The length of a key's next lockout after ``previous_lockouts`` earlier ones."""
        return min(self.lockout_s * 2.0 ** min(previous_lockouts, 64), self.max_lockout_s)
