"""One axis of a machine's compensation: its policy, macro, counters and write path.

A machine compensates one axis (the single-axis form: Z, written to
``compensation.macro``) or several (``compensation.axes``). Every cycle the loop
(:mod:`gateway.live.loop`) polls once, selects the regime once and hands each axis
its own prediction; the loop reads what every axis's macro holds in one request
(:meth:`CncClient.read_macros`), each :class:`Axis` lets its own
:class:`CompensationPolicy` decide (clamp, slew, deadband; with no prediction: hold,
then ramp to zero); the decided values go with :meth:`CncClient.write_macros_if`, each
guarded by a read of its macro right before its write (over OPC UA every axis's guard
in one Read and every write in one Write); the written macros are read back in one
request, and each axis counts its value as applied only once its read-back holds it.
An axis whose model is missing, or whose read or write fails, holds and ramps on its
own; the others keep compensating.

The handshake macro is one for the machine (:class:`HandshakeToken`): checked once
per cycle before the first write (a count the gateway did not write stops every
axis's write in that cycle) and bumped once after the cycle's confirmed writes.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence

from drivers.clock import Clock
from drivers.cnc import CncClient, CncError, GuardedWrite, MacroWrite
from drivers.yaml_loader import KeyPathError
from gateway.config import AxisSection, MachineSection
from gateway.live.bank.model_bank import ModelBank
from gateway.live.record import AxisRecord
from gateway.live.uncertainty_gate import UncertaintyGate
from gateway.live.writeback import CompensationPolicy, Decision
from models.online.regime_rules import RegimeRules

log = logging.getLogger(__name__)


class HandshakeToken:
    """``compensation.handshake_macro``: the machine's ownership token and write counter.

    Before the cycle's first write it must still hold the count the gateway wrote last;
    anything else (an operator or a CNC programme reset it) is an external change:
    no axis writes this cycle, and the next one moves on from what the CNC holds and
    writes a new count. With no count written yet (start, a failed handshake write)
    there is no token to check. One bump per cycle with a confirmed write.
    """

    def __init__(self, machine_id: str, macro: int | None, cnc: CncClient) -> None:
        self.machine_id = machine_id
        self.macro = macro
        self.cnc = cnc
        self.count = 0
        #: The count last written and answered (None: none, or unknown).
        self.written: float | None = None
        #: Resets of the token seen at the CNC.
        self.external_changes = 0
        self._verdict: tuple[str, str] | None = None  # this cycle's (kind, text)

    def new_cycle(self) -> None:
        self._verdict = None

    async def check(self, macros: Sequence[int]) -> tuple[str, str]:
        """("ours", ""), ("unread", why) or ("external", what the CNC holds): read once per
        cycle, at the first axis that writes; ``macros`` (the axes') name it in the log."""
        if self._verdict is None:
            self._verdict = await self._read(macros)
        return self._verdict

    async def _read(self, macros: Sequence[int]) -> tuple[str, str]:
        macro, ours = self.macro, self.written
        if macro is None or ours is None:
            return "ours", ""
        try:
            value = await self.cnc.read_macro(macro)
        except CncError as exc:
            return "unread", f"not written: {exc}"
        if value == ours:
            return "ours", ""
        self.written = None
        self.external_changes += 1
        note = f"external change: handshake macro #{macro} holds {value}, the gateway wrote {ours}"
        listed = ", ".join(f"#{m}" for m in macros)
        log.warning(
            "%s: %s; %s %s not written this cycle (external changes: %d)",
            self.machine_id,
            note,
            listed,
            "is" if len(macros) == 1 else "are",
            self.external_changes,
        )
        return "external", note

    async def bump(self) -> str:
        """After the cycle's confirmed writes: the next count, remembered as the token.

        Written only over the count the gateway wrote last (read in the same session, as
        the axes' macros are): a reset that landed since the token was checked stays at
        the CNC, and the next cycle's check sees it as any other reset. Returns what
        went wrong ("" when written or when there is no handshake macro).
        """
        macro = self.macro
        if macro is None:
            return ""
        previous, self.written = self.written, None
        self.count += 1
        count = float(self.count)
        try:
            if previous is None:  # no count of the gateway's there to keep
                await self.cnc.write_macro(macro, count)
            else:
                guarded = await self.cnc.write_macro_if(macro, count, lambda v: v == previous)
                if not guarded.written:
                    self.written = previous  # the next check finds the change
                    return (
                        f"handshake not written: #{macro} holds {guarded.held}, "
                        f"changed at the CNC since the gateway wrote {previous}"
                    )
        except CncError as exc:
            return f"handshake failed: {exc}"
        self.written = count
        return ""


class Axis:
    """One axis: the models it takes (per regime), its policy, gate, macro and counters."""

    def __init__(
        self,
        label: str,
        name: str,
        section: AxisSection,
        rules: RegimeRules,
        target: str | None,
        cnc: CncClient,
        clock: Clock,
    ) -> None:
        self.label = label  # how the log names this axis: the machine, or "machine axis X"
        self.name = name
        self.section = section
        self.rules = rules
        #: the error column every model of this axis predicts (None: the bank's one target)
        self.target = target
        self.cnc = cnc
        self.clock = clock
        self.policy: CompensationPolicy | None = None
        self.uncertainty_gate = UncertaintyGate(label, section.when_uncertain)
        self.failed_writes = 0
        self.external_changes = 0
        self.reached = False  # this cycle's read of the macro was answered
        self.confirmed = False  # this cycle's write was read back and confirmed
        self._external_note = ""  # this cycle's external change, for the write status

    @property
    def macro(self) -> int:
        return self.section.macro

    def model_for(self, regime: str | None) -> str | None:
        """The model id the regime rules name for this axis (None: no regime yet)."""
        return None if regime is None else self.rules.model_for(regime)

    # --- the write path -----------------------------------------------------------------
    # The loop reads every axis's macro in one request at the cycle start, writes the
    # axes that need it (each write guarded by a read right before it), then reads every
    # written macro back in one request: :meth:`decide`, :meth:`may_write`,
    # :meth:`guarded_write`, :meth:`written`, :meth:`confirm`.
    def decide(
        self,
        held: float | CncError,
        read_s: float,
        predicted: float | None,
        rec: AxisRecord,
        enabled: bool,
        on_disable: str,
    ) -> Decision | None:
        """From what the macro holds (read at ``read_s``, or why it was not read) and the
        prediction: start or update the policy and decide; the decision to write, or None
        (``rec`` says why).

        Nothing is decided to be written when the read failed: what the CNC holds is
        unknown, and the CNC never gets a value written blind. Times given to the policy
        are taken at the CNC (after the read, at the decision, after the read-back), not
        at the cycle start, so the slew limit holds between writes as the CNC receives
        them, however late a slow transmitter or link made a write.
        """
        self.confirmed = False
        self.reached = not isinstance(held, CncError)
        if self.policy is None:
            if isinstance(held, CncError):
                rec.write_status = f"waiting for the CNC: {self._unread(held)}"
                return None
            self._start_policy((read_s, held))
        elif not isinstance(held, CncError):
            self._observe_cnc((read_s, held), rec)
        policy = self.policy
        assert policy is not None
        rec.applied_um = policy.applied_um
        if not enabled and on_disable == "hold":
            policy.hold(self.clock.now())
            held_text = "unknown" if isinstance(held, CncError) else f"{policy.applied_um:.1f} µm"
            rec.write_status = self._status(f"disabled: #{self.macro} held at {held_text}")
            return None
        write_s = self.clock.now()
        predicted = self.uncertainty_gate.aim(predicted, rec.interval_um, policy.applied_um)
        rec.uncertain = self.uncertainty_gate.active
        decision = policy.decide(write_s, predicted, enabled=enabled)
        rec.target_um = decision.target_um
        if not decision.write:
            rec.write_status = self._status(f"no write: {decision.reason}")
            return None
        if isinstance(held, CncError):  # what the CNC holds is unknown: never write blind
            self._write_failed(write_s, f"not written: {self._unread(held)}", rec)
            return None
        return decision

    def may_write(self, handshake: tuple[str, str], rec: AxisRecord) -> bool:
        """The cycle's handshake verdict (:meth:`HandshakeToken.check`) lets this axis
        write; else ``rec`` and the counters say why not."""
        kind, text = handshake
        if kind == "unread":
            self._write_failed(self.clock.now(), text, rec)
            return False
        if kind == "external":
            self._external_note = "; ".join(filter(None, [self._external_note, text]))
            rec.write_status = self._status("not written: the handshake is not the gateway's")
            return False
        return True

    def guarded_write(self, decision: Decision) -> MacroWrite:
        """The decided value, to be written only over the value the gateway applied."""
        assert self.policy is not None
        return MacroWrite(self.macro, decision.value_cnc, self.policy.holds_applied)

    def written(self, guarded: GuardedWrite | CncError, rec: AxisRecord) -> bool:
        """The outcome of the guarded write (its read right before it, in the same
        session): True when written, to be read back and confirmed (:meth:`confirm`)."""
        if isinstance(guarded, CncError):
            self._write_failed(self.clock.now(), f"write failed: {guarded}", rec)
            return False
        if not guarded.written:  # changed since the cycle's read: the CNC's value stays
            self._observe_cnc((self.clock.now(), guarded.held), rec)
            rec.write_status = self._status(
                f"not written: #{self.macro} changed at the CNC just before the write"
            )
            return False
        return True

    def confirm(self, decision: Decision, read_back: float | CncError, rec: AxisRecord) -> None:
        """Count the written value as applied only if the CNC's read-back holds it."""
        policy = self.policy
        assert policy is not None
        confirmed_s = self.clock.now()
        if isinstance(read_back, CncError):
            self._write_failed(confirmed_s, f"write failed: {read_back}", rec)
            return
        if not policy.same_on_cnc(read_back, decision.value_cnc):
            self._write_failed(
                confirmed_s,
                f"read-back mismatch: wrote {decision.value_cnc}, CNC holds {read_back}",
                rec,
            )
            if math.isfinite(read_back):  # the CNC holds something else: that is the truth
                self._observe_cnc((confirmed_s, read_back), rec)
                rec.write_status = self._status(rec.write_status)
            return
        policy.confirm(confirmed_s, policy.from_cnc(read_back))
        rec.applied_um = policy.applied_um
        rec.written_cnc = decision.value_cnc
        rec.write_status = self._status(f"ok: {decision.reason}")
        self.confirmed = True

    def _status(self, text: str) -> str:
        """``text``, prefixed with this cycle's external change if there was one."""
        prefix, self._external_note = self._external_note, ""
        return f"{prefix}; {text}" if prefix else text

    def _unread(self, exc: CncError) -> str:
        return f"CNC macro #{self.macro} not read: {exc}"

    def _observe_cnc(self, held: tuple[float, float], rec: AxisRecord) -> None:
        """Compare what the CNC holds with what the gateway applied; log a change once."""
        assert self.policy is not None
        read_s, value = held
        change = self.policy.observe(read_s, value)
        rec.applied_um = self.policy.applied_um
        if change is None:
            return
        self.external_changes += 1
        note = (
            f"external change: CNC macro #{self.macro} holds {value} "
            f"({change.held_um:.1f} µm), the gateway had applied {change.believed_um:.1f} µm"
        )
        self._external_note = note
        self._warn_never_written(value)
        log.warning(
            "%s: %s; compensation moves on from the CNC's value at the slew limit "
            "(external changes: %d)",
            self.label,
            note,
            self.external_changes,
        )

    def _warn_never_written(self, value: float) -> bool:
        """Say so when the CNC holds a value the gateway would never write (beyond the
        clamp, infinite): a typo at the control (1.0 typed in mm where µm was meant) or
        a corrupted variable. The compensation moves from it within the clamp."""
        assert self.policy is not None
        why = self.policy.never_written(value)
        if why is None:
            return False
        log.warning(
            "%s: CNC macro #%d holds %r (%s): a value the gateway would never write; "
            "compensation moves from it back within the clamp",
            self.label,
            self.macro,
            value,
            why,
        )
        return True

    def _start_policy(self, held: tuple[float, float]) -> None:
        """The policy starts from what the CNC applies now (a vacant macro: 0)."""
        _, value = held
        limits = self.section.limits()
        probe = CompensationPolicy(limits)
        start_um = probe.from_cnc(value) if math.isfinite(value) else 0.0
        self.policy = CompensationPolicy(limits, start_um=start_um)
        if self._warn_never_written(value):
            self.external_changes += 1
        log.info(
            "%s: CNC macro #%d holds %s; compensation starts from %.2f µm",
            self.label,
            self.macro,
            value,
            start_um,
        )

    def _write_failed(self, now: float, reason: str, rec: AxisRecord) -> None:
        assert self.policy is not None
        self.policy.reject(now, reason)
        self.failed_writes += 1
        rec.applied_um = self.policy.applied_um
        rec.write_status = self._status(reason)
        log.warning("%s: %s (failed writes: %d)", self.label, reason, self.failed_writes)


def build_axes(
    machine: MachineSection, bank: ModelBank, cnc: CncClient, clock: Clock
) -> list[Axis]:
    """The machine's axes in the configured order (the single-axis form: one, Z)."""
    shared = machine.models.regimes.rules()
    targets = axis_targets(machine, bank)
    multi = machine.compensation.axes is not None
    axes = []
    for name, section in machine.axis_sections().items():
        rules = shared
        if multi:
            rules = dataclasses.replace(
                shared, models=dict(section.models), fallback_model=section.fallback_model
            )
        label = f"{machine.id} axis {name}" if multi else machine.id
        axes.append(Axis(label, name, section, rules, targets[name], cnc, clock))
    return axes


def axis_targets(machine: MachineSection, bank: ModelBank) -> dict[str, str | None]:
    """The error column each axis compensates (None: the single-axis form, whose bank holds
    one target). Refused, at the axis's key: an axis whose models predict another target
    than its ``target`` or than each other, an axis no model of the store serves, and two
    axes compensating one target."""
    axes = machine.compensation.axes
    if axes is None:
        return dict.fromkeys(machine.axis_sections())
    targets: dict[str, str | None] = {}
    owners: dict[str, str] = {}
    for name, axis in axes.items():
        target = _axis_target(name, axis, bank)
        where: tuple[str, ...] = ("compensation", "axes", name, "target")
        if axis.target is None:
            where = ("compensation", "axes", name, *next(iter(axis.named_models())).split("."))
        if not any(m.target.name == target for m in bank.models.values()):
            raise KeyPathError(
                where, f"no model in {machine.models.store} predicts {target} (axis {name})"
            )
        if target in owners:
            raise KeyPathError(
                where,
                f"axis {name} would compensate {target}, which axis {owners[target]} "
                "compensates: each axis its own error column",
            )
        owners[target] = name
        targets[name] = target
    return targets


def _axis_target(name: str, axis: AxisSection, bank: ModelBank) -> str:
    """The target of axis ``name``: its ``target``, else what its first named model predicts;
    every model it names must predict it."""
    target = axis.target
    for key, model_id in axis.named_models().items():
        predicts = bank.get(model_id).target.name
        if target is None:
            target = predicts
        elif predicts != target:
            raise KeyPathError(
                ("compensation", "axes", name, *key.split(".")),
                f"model '{model_id}' predicts {predicts}, but axis {name} compensates "
                f"{target}; every model of an axis predicts its target",
            )
    if target is None:
        raise KeyPathError(
            ("compensation", "axes", name),
            "names no model and no target: give fallback_model (or target)",
        )
    return target
