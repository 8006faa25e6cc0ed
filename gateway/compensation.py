"""The value written to the CNC: bounded, rate-limited, and safe when things fail.

A prediction is only a wish. What reaches the CNC's macro variable must never
exceed what the machine's owner allowed (``clamp_um``), must never move the tool
faster than ``slew_um_per_min`` (a sudden step leaves a visible step on the part),
and must not chatter the CNC with changes below its precision (``deadband_um``).
Each cycle :meth:`CompensationPolicy.decide` turns a prediction into a
:class:`Decision` in this order:

1. no usable prediction (None, NaN, inf): aim for 0 µm at the fallback ramp
   rate. The last applied value is held and wound down slowly rather than
   dropped, because a jump back to zero is as bad for the part as any jump;
2. clamp the aim to ±clamp_um;
3. limit the change from the last *applied* (confirmed) value to the slew rate
   times the minutes since it was applied. Measuring from the applied value
   means a failed write cannot make the next step larger than the rate allows,
   and a write suppressed by the deadband still lets the budget grow until the
   change is worth writing. The budget never exceeds the deadband plus one CNC
   step plus one cycle's worth, though: otherwise a long hold inside the
   deadband would bank minutes of slew and release them as one step the
   moment the prediction jumps (e.g. at a model switch);
4. round to the CNC's precision; the clamp is taken to the largest CNC step
   inside it, so rounding can never carry a value past it;
5. write only if the rounded target differs from the applied value, by at least
   the deadband. The very first decision always writes (the clamped start
   value, unchanged): it puts the CNC in a state the gateway knows.

The caller writes, reads back, and reports with :meth:`confirm` (the read-back
value becomes the applied value) or :meth:`reject` (nothing changes). Times are
machine seconds passed in by the caller; no I/O happens here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

__all__ = ["CompensationLimits", "CompensationPolicy", "Decision"]

_UM_PER_UNIT = {"mm": 1000.0, "um": 1.0}


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
    """

    clamp_um: float = 50.0
    slew_um_per_min: float = 20.0
    deadband_um: float = 0.5
    unit: Literal["mm", "um"] = "mm"
    sign: Literal[1, -1] = 1
    decimals: int = 4
    fallback_ramp_um_per_min: float | None = None

    def __post_init__(self) -> None:
        if self.unit not in _UM_PER_UNIT:
            raise ValueError(f"CompensationLimits.unit must be 'mm' or 'um', got {self.unit!r}")
        if self.sign not in (1, -1) or isinstance(self.sign, bool):
            raise ValueError(f"CompensationLimits.sign must be 1 or -1, got {self.sign!r}")
        if not isinstance(self.decimals, int) or isinstance(self.decimals, bool):
            raise ValueError(f"CompensationLimits.decimals must be an int, got {self.decimals!r}")
        if not 0 <= self.decimals <= 9:
            raise ValueError(f"CompensationLimits.decimals must be in 0..9, got {self.decimals}")
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

    @property
    def step_um(self) -> float:
        """One step of the CNC's precision, in µm."""
        return _UM_PER_UNIT[self.unit] / 10**self.decimals

    @property
    def ramp_um_per_min(self) -> float:
        """Rate of the ramp to zero when there is no prediction."""
        ramp = self.fallback_ramp_um_per_min
        return self.slew_um_per_min if ramp is None else ramp


@dataclass(frozen=True)
class Decision:
    """What to do with the CNC this cycle.

    Attributes:
        target_um: the value to apply now, after clamp, slew and rounding to the
            CNC's precision (µm, predicted-error sign).
        write: False when the change is within the deadband.
        value_cnc: ``target_um`` in the CNC's unit and sign, rounded: what to write.
        reason: why, e.g. "tracking", "clamped at +50.0 µm, slew-limited",
            "no prediction: ramping to zero, within deadband", "first write".
    """

    target_um: float
    write: bool
    value_cnc: float
    reason: str


class CompensationPolicy:
    """Turns predictions into CNC writes (see the module docstring)."""

    def __init__(self, limits: CompensationLimits, start_um: float = 0.0) -> None:
        """``start_um``: what the CNC holds now (read back at start-up), µm."""
        if not math.isfinite(start_um):
            raise ValueError(f"start_um must be finite, got {start_um}")
        self.limits = limits
        self.failed_writes = 0
        self.last_failure: str | None = None
        self._applied_um = float(start_um)
        self._applied_s: float | None = None  # the slew budget starts at the first decision
        self._last_decision_s: float | None = None
        self._last_s: float | None = None
        self._confirmed_once = False
        steps = math.floor(limits.clamp_um / limits.step_um + 1e-9)
        self._clamp_um = self._round_um(steps * limits.step_um)

    @property
    def applied_um(self) -> float:
        """The value the CNC holds, as last confirmed (or ``start_um``), µm."""
        return self._applied_um

    def to_cnc(self, um: float) -> float:
        """µm (predicted-error sign) -> CNC unit and sign, rounded to ``decimals``."""
        lim = self.limits
        return round(lim.sign * um / _UM_PER_UNIT[lim.unit], lim.decimals) + 0.0

    def from_cnc(self, value: float) -> float:
        """CNC unit and sign -> µm (predicted-error sign), on the CNC's grid."""
        lim = self.limits
        return self._round_um(lim.sign * value * _UM_PER_UNIT[lim.unit])

    def decide(self, now_s: float, predicted_um: float | None) -> Decision:
        """The value to apply at ``now_s`` for this prediction (None: no prediction)."""
        self._advance(now_s)
        lim = self.limits
        if self._applied_s is None:
            self._applied_s = now_s
        previous_s = now_s if self._last_decision_s is None else self._last_decision_s
        self._last_decision_s = now_s
        first = not self._confirmed_once
        applied = self._applied_um

        reasons = ["first write"] if first else []
        usable = predicted_um is not None and math.isfinite(predicted_um)
        if usable:
            assert predicted_um is not None
            aim_um, rate = predicted_um, lim.slew_um_per_min
        else:
            aim_um, rate = 0.0, lim.ramp_um_per_min
            got = "" if predicted_um is None else f" ({predicted_um})"
            reasons.append(f"no prediction{got}: ramping to zero")

        clamped = self._clamp(aim_um)
        if clamped != aim_um:
            reasons.append(f"clamped at {clamped:+.1f} µm")
        banked_um = rate * (now_s - self._applied_s) / 60.0
        cap_um = rate * (now_s - previous_s) / 60.0 + lim.deadband_um + lim.step_um
        budget_um = min(banked_um, cap_um)
        limited = applied + max(-budget_um, min(budget_um, clamped - applied))
        if usable and limited != clamped:
            reasons.append("slew-limited")
        # The applied value may lie outside the clamp (start_um): the clamp wins.
        value_cnc = self.to_cnc(self._clamp(limited))
        target_um = self.from_cnc(value_cnc)

        change_um = abs(target_um - applied)
        write = first or (change_um > 0.0 and change_um >= lim.deadband_um)
        if not write:
            reasons.append("within deadband")
        if not reasons:
            reasons.append("tracking")
        return Decision(target_um, write, value_cnc, ", ".join(reasons))

    def confirm(self, now_s: float, applied_um: float) -> None:
        """A write succeeded and read back ``applied_um`` (µm): it is now applied."""
        self._advance(now_s)
        if not math.isfinite(applied_um):
            raise ValueError(f"applied_um must be finite, got {applied_um}")
        self._applied_um = float(applied_um)
        self._applied_s = now_s
        self._confirmed_once = True

    def reject(self, now_s: float, reason: str) -> None:
        """A write failed: the applied value stays the last confirmed one."""
        self._advance(now_s)
        self.failed_writes += 1
        self.last_failure = reason

    def _advance(self, now_s: float) -> None:
        if not math.isfinite(now_s):
            raise ValueError(f"now_s must be finite, got {now_s}")
        if self._last_s is not None and now_s < self._last_s:
            raise ValueError(f"now_s went back: {now_s} after {self._last_s}")
        self._last_s = now_s

    def _clamp(self, um: float) -> float:
        return min(max(um, -self._clamp_um), self._clamp_um)

    def _round_um(self, um: float) -> float:
        """Round µm to the CNC's grid (decimals in its unit)."""
        digits = self.limits.decimals - (3 if self.limits.unit == "mm" else 0)
        return round(um, digits) + 0.0
