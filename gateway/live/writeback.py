"""The value written to the CNC: bounded, rate-limited, and safe when things fail.

A prediction is only a wish. What reaches the CNC's macro variable must never
exceed what the machine's owner allowed (``clamp_um``), must never move the tool
faster than ``slew_um_per_min`` (a sudden step leaves a visible step on the part),
and must not chatter the CNC with changes below its precision (``deadband_um``).
Each cycle :meth:`CompensationPolicy.decide` turns a prediction into a
:class:`Decision` in this order:

1. no usable prediction (None, NaN, inf): hold the applied value for
   ``hold_on_loss_s`` after the last cycle that had one (a missed transmitter
   read must not move the tool), then aim for 0 µm at the fallback ramp rate.
   The value is wound down slowly rather than dropped, because a jump back to
   zero is as bad for the part as any jump. With ``enabled=False`` (the
   operator switched compensation off and chose ``ramp``) the aim is 0 µm at
   the slew rate, at once;
2. clamp the aim to ±clamp_um;
3. limit the change from the last *applied* (confirmed) value to the slew rate
   times the minutes since it was applied. Measuring from the applied value
   means a failed write cannot make the next step larger than the rate allows,
   and a write suppressed by the deadband still lets the budget grow until the
   change is worth writing. The budget never exceeds the deadband plus one CNC
   step plus one cycle's worth, though: otherwise a long hold inside the
   deadband would bank minutes of slew and release them as one step the
   moment the prediction jumps (e.g. at a model switch);
4. round to the CNC's precision, never past the slew budget (the step is taken
   to the CNC grid point on the applied value's side); the clamp is taken to
   the largest CNC step inside it, so rounding can never carry a value past it;
5. write only if the rounded target differs from the applied value, by at least
   the deadband (a ramp to zero always writes its final 0). The very first
   decision always writes (the clamped start value, unchanged): it puts the
   CNC in a state the gateway knows.

The slew is what the CNC feels between two writes, so the caller passes the
time of the write to :meth:`decide` (taken right before writing) and the time
of the read-back to :meth:`confirm`: the budget of the next step then counts
from a moment after the CNC had the previous value, however late a slow link
made either write.

The CNC's macro is the truth. Before deciding, the caller reads it and hands it
to :meth:`observe`; a value the gateway did not write (an operator cleared it,
the CNC restarted holding 0) becomes the applied value, with the slew budget
restarting from the moment it was seen, so the compensation moves on from what
the CNC holds at the slew limit and never steps back to the old value.

Right before writing, the caller reads the macro once more on the write's own
session and writes only if :meth:`holds_applied` says it still holds the applied
value; otherwise it hands that value to :meth:`observe` (an external change) and
writes nothing. :meth:`never_written` names a held value the policy could never have
written (beyond the clamp, infinite), for a warning.

The caller writes, reads back, and reports with :meth:`confirm` (the read-back
value becomes the applied value) or :meth:`reject` (nothing changes; a write
that did land after all is recognised by the next :meth:`observe`). Times are
machine seconds passed in by the caller; no I/O happens here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gateway.limits import UM_PER_UNIT, CompensationLimits

__all__ = ["CompensationPolicy", "Decision", "ExternalChange"]

_EPS_UM = 1e-9  # float noise allowed when comparing µm values against a budget


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


@dataclass(frozen=True)
class ExternalChange:
    """The CNC held a value the gateway did not write (seen by :meth:`CompensationPolicy.observe`).

    Attributes:
        believed_um: what the gateway had applied (µm, predicted-error sign).
        held_um: what the CNC holds, on its grid (µm); now the applied value.
        held_cnc: the raw value read, in the CNC's unit and sign (NaN: a vacant macro).
    """

    believed_um: float
    held_um: float
    held_cnc: float


class CompensationPolicy:
    """Turns predictions into CNC writes (see the module docstring)."""

    def __init__(self, limits: CompensationLimits, start_um: float = 0.0) -> None:
        """``start_um``: what the CNC holds now (read back at start-up), µm."""
        if not math.isfinite(start_um):
            raise ValueError(f"start_um must be finite, got {start_um}")
        self.limits = limits
        self.failed_writes = 0
        self.external_changes = 0
        self.last_failure: str | None = None
        self._applied_um = float(start_um)
        self._applied_s: float | None = None  # the slew budget starts at the first decision
        self._last_decision_s: float | None = None
        self._last_usable_s: float | None = None  # last decision with a prediction
        self._last_s: float | None = None
        self._confirmed_once = False
        self._proposed_um: float | None = None  # target of the latest decision
        self._pending_um: float | None = None  # a rejected write that may have landed
        steps = math.floor(limits.clamp_um / limits.step_um + 1e-9)
        self._clamp_um = self._round_um(steps * limits.step_um)

    @property
    def applied_um(self) -> float:
        """The value the CNC holds, as last confirmed or observed (or ``start_um``), µm."""
        return self._applied_um

    def to_cnc(self, um: float) -> float:
        """µm (predicted-error sign) -> CNC unit and sign, rounded to ``decimals``."""
        lim = self.limits
        return round(lim.sign * um / UM_PER_UNIT[lim.unit], lim.decimals) + 0.0

    def from_cnc(self, value: float) -> float:
        """CNC unit and sign -> µm (predicted-error sign), on the CNC's grid."""
        lim = self.limits
        return self._round_um(lim.sign * value * UM_PER_UNIT[lim.unit])

    def same_on_cnc(self, read_cnc: float, expected_cnc: float) -> bool:
        """Whether a value read from the CNC is ``expected_cnc`` within the CNC's rounding.

        Half a step of the CNC's precision, plus a relative part for a macro
        carried as float32 (Modbus) rather than as a double.
        """
        tolerance = 0.5 * 10.0 ** (-self.limits.decimals) + 1e-6 * abs(expected_cnc)
        return math.isfinite(read_cnc) and abs(read_cnc - expected_cnc) <= tolerance

    def holds_applied(self, held_cnc: float) -> bool:
        """Whether ``held_cnc`` (read from the CNC) is the applied value, as :meth:`observe`
        judges it: within the CNC's rounding, a vacant macro (NaN) counting as 0.

        The write path reads the macro once more right before each write and writes
        only when this holds: a different value was put there by someone else since
        the cycle's first read, and must not be overwritten unseen.
        """
        value = held_cnc if math.isfinite(held_cnc) else 0.0
        return self.same_on_cnc(value, self.to_cnc(self._applied_um))

    def never_written(self, held_cnc: float) -> str | None:
        """Why the gateway would never have written ``held_cnc``, or None when it might have.

        Beyond the clamp (1e30, or 1.0 typed into a macro in mm where µm was meant)
        or infinite. A vacant macro (NaN) is not such a value: the CNC reads it as 0.
        """
        if math.isnan(held_cnc):
            return None
        if math.isinf(held_cnc):
            return "not a finite number"
        held_um = self.limits.sign * held_cnc * UM_PER_UNIT[self.limits.unit]
        if abs(held_um) > self._clamp_um + 0.5 * self.limits.step_um:
            return f"{held_um:.4g} µm, beyond the ±{self._clamp_um:g} µm clamp"
        return None

    def observe(self, now_s: float, held_cnc: float) -> ExternalChange | None:
        """What the CNC holds at ``now_s`` (its unit and sign), read before deciding.

        The same as the applied value (within the CNC's rounding): nothing
        changes. The value of a write reported as failed: it did land, and
        counts as applied from ``now_s``. Anything else was written by someone
        else; it becomes the applied value, the slew budget restarts at
        ``now_s`` and the change is returned (and counted in
        ``external_changes``). A vacant macro (NaN) acts as 0, as on the CNC.
        """
        self._advance(now_s)
        value = held_cnc if math.isfinite(held_cnc) else 0.0
        pending, self._pending_um = self._pending_um, None
        if self.same_on_cnc(value, self.to_cnc(self._applied_um)):
            return None
        if pending is not None and self.same_on_cnc(value, self.to_cnc(pending)):
            self._set_applied(now_s, pending)
            self._confirmed_once = True
            return None
        change = ExternalChange(self._applied_um, self.from_cnc(value), float(held_cnc))
        self._set_applied(now_s, change.held_um)
        self.external_changes += 1
        return change

    def hold(self, now_s: float) -> None:
        """The gateway leaves the CNC alone this cycle (compensation off, ``hold``).

        The slew budget restarts at ``now_s``, so nothing is banked while the
        gateway does not write: switched on again, it moves at the slew rate. So
        does the hold on loss of prediction: switched on without one, the value
        is held ``hold_on_loss_s`` from then before the ramp to zero.
        """
        self._advance(now_s)
        self._applied_s = now_s
        self._last_decision_s = now_s
        self._last_usable_s = now_s

    def decide(self, now_s: float, predicted_um: float | None, *, enabled: bool = True) -> Decision:
        """The value to write at ``now_s`` for this prediction (None: no prediction).

        ``now_s`` is the time of the write (taken right before it). With
        ``enabled=False`` the aim is 0 µm at the slew rate (compensation
        switched off, ``on_disable: ramp``).
        """
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
        if usable or self._last_usable_s is None:
            self._last_usable_s = now_s  # with no prediction ever, the loss starts now
        budget_from_s = self._applied_s
        to_zero = True
        if not enabled:
            aim_um, rate = 0.0, lim.slew_um_per_min
            reasons.append("compensation disabled: ramping to zero")
        elif usable:
            assert predicted_um is not None
            aim_um, rate, to_zero = predicted_um, lim.slew_um_per_min, False
        else:
            got = "" if predicted_um is None else f" ({predicted_um})"
            ramp_from_s = self._last_usable_s + lim.hold_on_loss_s
            if now_s < ramp_from_s:
                aim_um, rate, to_zero = applied, lim.ramp_um_per_min, False
                lost_s = now_s - self._last_usable_s
                held = f"holding for {lim.hold_on_loss_s:g} s ({lost_s:g} s so far)"
                reasons.append(f"no prediction{got}: {held}")
            else:
                aim_um, rate = 0.0, lim.ramp_um_per_min
                budget_from_s = max(budget_from_s, ramp_from_s)
                reasons.append(f"no prediction{got}: ramping to zero")

        clamped = self._clamp(aim_um)
        if clamped != aim_um:
            reasons.append(f"clamped at {clamped:+.1f} µm")
        banked_um = rate * max(0.0, now_s - budget_from_s) / 60.0
        cap_um = rate * (now_s - previous_s) / 60.0 + lim.deadband_um + lim.step_um
        budget_um = min(banked_um, cap_um)
        limited = applied + max(-budget_um, min(budget_um, clamped - applied))
        if usable and enabled and limited != clamped:
            reasons.append("slew-limited")
        # The applied value may lie outside the clamp (start_um, an external change):
        # the clamp wins over the slew budget.
        grid_um = self._clamp(self._grid_within(limited, applied - budget_um, applied + budget_um))
        value_cnc = self.to_cnc(grid_um)
        target_um = self.from_cnc(value_cnc)

        change_um = abs(target_um - applied)
        worth = change_um >= lim.deadband_um or (to_zero and target_um == 0.0)
        write = first or (change_um > 0.0 and worth)
        if not write:
            reasons.append("within deadband")
        if not reasons:
            reasons.append("tracking")
        self._proposed_um = target_um
        return Decision(target_um, write, value_cnc, ", ".join(reasons))

    def confirm(self, now_s: float, applied_um: float) -> None:
        """A write succeeded and read back ``applied_um`` (µm) at ``now_s``: it is now applied."""
        self._advance(now_s)
        if not math.isfinite(applied_um):
            raise ValueError(f"applied_um must be finite, got {applied_um}")
        self._set_applied(now_s, float(applied_um))
        self._confirmed_once = True
        self._pending_um = None

    def reject(self, now_s: float, reason: str) -> None:
        """A write failed: the applied value stays the last confirmed one.

        The write may still have reached the CNC (a reply lost on the way back):
        the next :meth:`observe` that finds its value takes it as applied rather
        than as an external change.
        """
        self._advance(now_s)
        self.failed_writes += 1
        self.last_failure = reason
        self._pending_um = self._proposed_um

    def _set_applied(self, now_s: float, applied_um: float) -> None:
        self._applied_um = applied_um
        self._applied_s = now_s

    def _advance(self, now_s: float) -> None:
        if not math.isfinite(now_s):
            raise ValueError(f"now_s must be finite, got {now_s}")
        if self._last_s is not None and now_s < self._last_s:
            raise ValueError(f"now_s went back: {now_s} after {self._last_s}")
        self._last_s = now_s

    def _clamp(self, um: float) -> float:
        return min(max(um, -self._clamp_um), self._clamp_um)

    def _grid_within(self, um: float, low_um: float, high_um: float) -> float:
        """``um`` on the CNC grid: the nearest point, or the nearest one inside [low, high].

        Rounding to the nearest point could carry a slew-limited step past its
        budget by half a step; the point on the applied value's side is taken
        then. When no grid point lies inside (a budget below one step around an
        off-grid start value), the nearest one is returned.
        """
        nearest = self._round_um(um)
        if low_um - _EPS_UM <= nearest <= high_um + _EPS_UM:
            return nearest
        step = self.limits.step_um
        if nearest > high_um:
            inside = self._round_um(math.floor(high_um / step + 1e-9) * step)
        else:
            inside = self._round_um(math.ceil(low_um / step - 1e-9) * step)
        return inside if low_um - _EPS_UM <= inside <= high_um + _EPS_UM else nearest

    def _round_um(self, um: float) -> float:
        """Round µm to the CNC's grid (decimals in its unit)."""
        digits = self.limits.decimals - (3 if self.limits.unit == "mm" else 0)
        return round(um, digits) + 0.0
