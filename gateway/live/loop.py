"""The per-machine compensation loop: read, check, select, predict, write safely.

Once per ``cycle_s`` of machine time:

1. read every transmitter bus and the spindle speed, concurrently; a silent
   device or a dead link becomes missing values and a health record, never an
   exception through the loop;
2. flag each sensor's quality (range, rate, stuck, stale, transmitter fault,
   and plausibility against the other sensors, :mod:`gateway.live.plausibility`);
3. classify the speed regime (with hysteresis, once for every axis) and take each
   axis's model for it from the bank, or a fallback of the same target fitted without
   a bad sensor, or none (:mod:`gateway.live.axis`: one machine compensates one axis,
   Z, or every axis of ``compensation.axes``);
4. predict the error rise (µm) from the temperature rises above the cold reference;
   every augmented model (lag terms, :mod:`gateway.live.bank.lag_state`) is advanced
   with this cycle's rises and speed whether it is selected or not, so a model
   switched in mid-shift has a warm state;
5. read what every axis's CNC macro holds, in one request (a value the gateway did
   not write is an external change: logged, counted, and the policy moves on from
   it); for each axis in the configured order let its compensation policy decide the
   value (clamp, slew, deadband; with no prediction it holds, then ramps to zero) and
   write it to the macro, guarded by a read of that macro right before the write
   (over OPC UA every axis's guard in one Read, every write in one Write);
   read every written macro back in one request, and only then count each value as
   applied; then bump the handshake counter once for the cycle's confirmed writes;
6. write the next alive count (``compensation.alive_macro``), the CNC's sign that
   the gateway runs and reaches it, in every cycle the CNC answered.

Nothing is written before the loop has read what the CNC macro holds, in the
same cycle, so the slew limit starts from the value the machine really applies.
The prediction rate bound (:meth:`Plausibility.check_prediction`), the probe, the
online correction and the residual monitor work on the first axis; a sensor the
rate bound blames is left out for every axis.
Every cycle ends as a :class:`CycleRecord` handed to the sinks (logging, SCADA,
tests).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from drivers.clock import Clock
from drivers.cnc import CncClient, CncError, GuardedWrites, MacroReads, MacroWrite
from drivers.transmitters import ChannelResult, TransmitterBus
from gateway.config import MachineSection
from gateway.live.axis import Axis, HandshakeToken, build_axes
from gateway.live.bank.lag_state import EffectStates, WarmLags
from gateway.live.bank.model_bank import Banked, BankedAugmented, ModelBank
from gateway.live.bank.promotion import Promotions
from gateway.live.interval import assess, interval_nominal
from gateway.live.plausibility import Plausibility
from gateway.live.quality import Quality, QualityMonitor, SensorCheck
from gateway.live.record import AxisRecord, CycleRecord, Sink, sink_name
from gateway.live.reference import TemperatureReference
from gateway.live.scheduler import CycleScheduler, after_cycle
from gateway.live.uncertainty_gate import UncertaintyGate
from gateway.live.writeback import CompensationPolicy, Decision
from gateway.process.file_writer import STATE
from models.base import ModelInputs
from models.data.dataset import ambient_sensor_of
from models.fit.interval import with_probe_age
from models.online.correction import CorrectionParams, OnlineCorrection
from models.online.regime_rules import RegimeSelector, Selection

log = logging.getLogger(__name__)

T = TypeVar("T")
S = TypeVar("S")


#: Wall seconds a cycle in progress may take to finish once a stop is requested.
STOP_GRACE_S = 0.5
#: How long a closing loop waits for its last lag-state save to reach the disk, s.
STATE_FLUSH_S = 5.0
#: The alive count runs 1…ALIVE_WRAP and starts again at 1: far below what a macro holds.
ALIVE_WRAP = 9999


#: The per-axis fields of a record: the record's own repeat the first axis's.
_AXIS_FIELDS = (
    "model_id",
    "predicted_um",
    "target_um",
    "applied_um",
    "written_cnc",
    "write_status",
    "correction_um",
    "interval_um",
    "training_span",
    "outside_inputs",
    "uncertain",
)


@dataclass
class _Inputs:
    """This cycle's inputs every axis predicts from (the good set shrinks if the rate
    bound blames a sensor)."""

    good: set[str]
    good_values: dict[str, float]
    speed_rpm: float | None
    augmented_um: Mapping[str, float | None]


def next_alive_count(count: int) -> int:
    """The alive count after ``count`` (0: none written yet): never 0, so a macro the CNC
    cleared at power-on is told apart from a gateway that writes."""
    return count % ALIVE_WRAP + 1


class MachineLoop:
    def __init__(
        self,
        config: MachineSection,
        clock: Clock,
        buses: Sequence[TransmitterBus],
        cnc: CncClient,
        bank: ModelBank,
        state_dir: Path | None = None,
        sinks: Sequence[Sink] = (),
    ) -> None:
        self.config = config
        self.clock = clock
        self.buses = list(buses)
        self.cnc = cnc
        self.bank = bank
        self.sinks = list(sinks)
        self.sensors = config.sensor_names
        self.plausibility = Plausibility.for_machine(
            config.id, bank, self.sensors, config.plausibility.limits()
        )
        self.quality = QualityMonitor(self.sensors, config.quality_limits(), self.plausibility)
        self.selector = RegimeSelector(config.models.regimes.rules())
        reference = config.models.reference
        state_file = None if state_dir is None else state_dir / f"{config.id}-reference.json"
        self.reference = TemperatureReference(
            reference.mode, reference.values_C, state_file, writer=STATE
        )
        effect_file = None if state_dir is None else state_dir / f"{config.id}-effect-state.json"
        #: The promoted set of the store, swapped into the bank between cycles.
        self.promotions = Promotions(config, running=True)
        self.promotions.load(bank)
        warm = WarmLags(self.sensors, ambient_sensor_of(self.sensors))
        self.effects = EffectStates(bank.augmented(), effect_file, warm=warm, writer=STATE)
        self.compensation_enabled = config.compensation.enabled
        #: Every axis compensated, in the configured order (the single-axis form: one, Z).
        self.axes = build_axes(config, bank, cnc, clock)
        self.handshake_token = HandshakeToken(config.id, config.compensation.handshake_macro, cnc)
        self._machine_failed_writes = 0  # writes of no axis's (the alive count)
        self.cycles = 0
        #: Link errors reported, summed over cycles (one per failing source per cycle).
        self.link_errors = 0
        #: Failures per sink (by name); a failing sink never stops the cycle.
        self.sink_failures: dict[str, int] = {}
        self._failing_sinks: set[str] = set()
        self._last_probe_um: float | None = None
        online = config.online_correction
        self.online = OnlineCorrection(online.params()) if online.enabled else None
        self._probe_basis: tuple[float, float] | None = None  # (predicted, applied) µm, last cycle
        self._link_down: set[str] = set()
        self._reverse_noted = False  # a negative (reverse) spindle speed was logged once
        #: The alive count the CNC last acknowledged (0: none yet).
        self.alive = 0
        self._alive_failing = False  # an alive write failed; logged once until one works
        #: Machine time the cycle in progress (or the last one) was due at.
        self.due_s = 0.0
        #: How long after its due time that cycle started, s (the event loop's delay:
        #: the scheduler's tick, the loops released before it, any work holding the loop).
        self.start_late_s = 0.0

    # --- counters and the primary axis ------------------------------------------------
    @property
    def primary(self) -> Axis:
        """The first axis: the record's own fields, the probe, the online correction."""
        return self.axes[0]

    @property
    def policy(self) -> CompensationPolicy | None:
        return self.primary.policy

    @property
    def uncertainty_gate(self) -> UncertaintyGate:
        return self.primary.uncertainty_gate

    @property
    def failed_writes(self) -> int:
        """Failed writes of every axis, and of the alive count."""
        return self._machine_failed_writes + sum(axis.failed_writes for axis in self.axes)

    @property
    def external_changes(self) -> int:
        """External changes of every axis's macro, and of the handshake token."""
        own = sum(axis.external_changes for axis in self.axes)
        return own + self.handshake_token.external_changes

    @property
    def handshake(self) -> int:
        """The handshake count last bumped."""
        return self.handshake_token.count

    # --- one cycle ----------------------------------------------------------------------
    async def run_cycle(self) -> CycleRecord:
        self._swap_promoted()
        now = self.clock.now()
        stamp_s = self.clock.stamp()  # the one wall time every output gives this cycle
        results, speed_rpm, errors = await self._read_inputs(now)
        self.link_errors += len(errors)
        readings = {
            name: (results[name].value_C, results[name].status) if name in results else (None, None)
            for name in self.sensors
        }
        checks = self.quality.check(now, readings, self.reference.values_C)
        good = {n for n, c in checks.items() if c.quality is Quality.GOOD}
        good_values = {n: value for n in good if (value := readings[n][0]) is not None}
        self.reference.observe(good_values, speed_rpm)
        self.plausibility.reference_turning = self.reference.taken_turning
        augmented_um = self.effects.advance(
            now, self.reference.available_rises_C(good_values), speed_rpm
        )
        selection = self.selector.update(now, speed_rpm) if speed_rpm is not None else None
        regime = selection.regime if selection else None
        if selection is not None and selection.switched:
            self._log_switch(selection)
        inputs = _Inputs(good, good_values, speed_rpm, augmented_um)
        banked, predicted = self._checked_primary(now, regime, inputs, checks)
        record = CycleRecord(
            machine=self.config.id,
            time_s=now,
            temperatures_C={n: readings[n][0] for n in self.sensors},
            quality={n: c.quality.value for n, c in checks.items()},
            quality_reasons={n: c.reason for n, c in checks.items() if c.reason},
            speed_rpm=speed_rpm,
            regime=regime,
            model_id=None,
            predicted_um=None,
            target_um=None,
            applied_um=None,
            written_cnc=None,
            write_status="",
            link_errors=errors,
            stamp_s=stamp_s,
        )
        bad = sum(1 for c in checks.values() if c.quality is not Quality.GOOD)
        aims = [
            self._axis_aim(now, axis, regime, inputs, bad, banked, predicted) for axis in self.axes
        ]
        await self._compensate_axes(aims, record)
        await self._write_alive(record)
        await self._read_probe(record)
        self._online_update(now, predicted, record)
        self.cycles += 1
        self._deliver(record)
        return record

    def _log_switch(self, selection: Selection) -> None:
        if self.config.compensation.axes is None:
            served = f"model {selection.model_id}"
        else:
            served = ", ".join(f"{a.name} {a.model_for(selection.regime)}" for a in self.axes)
        log.info(
            "%s: regime %s → %s (%s)", self.config.id, selection.regime, served, selection.reason
        )

    def _checked_primary(
        self, now: float, regime: str | None, inputs: _Inputs, checks: dict[str, SensorCheck]
    ) -> tuple[Banked | None, float | None]:
        """The first axis's model and prediction, checked against the prediction rate bound
        (:meth:`Plausibility.check_prediction`): a sensor whose own step moved it faster than
        heat can is marked implausible for every axis, and the prediction made without it.
        The other axes are predicted from the good sensors that remain."""
        axis = self.primary
        model_id = axis.model_for(regime)
        banked = self.bank.usable(model_id, inputs.good, axis.target)
        predicted = self._predict(banked, inputs)
        rises = self.reference.available_rises_C(inputs.good_values)
        suspect = self.plausibility.check_prediction(now, banked, rises, inputs.speed_rpm)
        if suspect is not None:  # moved faster than heat can: not used; predict without it
            checks[suspect.sensor] = self.quality.mark_implausible(suspect.sensor, suspect.reason)
            inputs.good.discard(suspect.sensor)
            inputs.good_values.pop(suspect.sensor, None)
            banked = self.bank.usable(model_id, inputs.good, axis.target)
            predicted = self._predict(banked, inputs)
        self.plausibility.accept(
            now, self.reference.available_rises_C(inputs.good_values), inputs.speed_rpm
        )
        return banked, predicted

    def _axis_aim(
        self,
        now: float,
        axis: Axis,
        regime: str | None,
        inputs: _Inputs,
        bad: int,
        primary: Banked | None,
        primary_um: float | None,
    ) -> tuple[Axis, AxisRecord, float | None]:
        """One axis's model, prediction and interval; its aim (the first axis's with the
        online correction added)."""
        if axis is self.primary:
            banked, predicted = primary, primary_um
        else:
            banked = self.bank.usable(axis.model_for(regime), inputs.good, axis.target)
            predicted = self._predict(banked, inputs)
        rec = AxisRecord(
            axis=axis.name,
            macro=axis.macro,
            model_id=banked.model_id if banked else None,
            predicted_um=predicted,
        )
        rises = self.reference.available_rises_C(inputs.good_values)
        interval = assess(banked, predicted, rises, inputs.speed_rpm, bad)
        rec.interval_um = interval.half_width_um
        rec.training_span = interval.span
        rec.outside_inputs = interval.outside_inputs
        if axis is self.primary:
            predicted = self._corrected(now, banked, predicted, rec)
        return axis, rec, predicted

    async def _compensate_axes(
        self, aims: Sequence[tuple[Axis, AxisRecord, float | None]], record: CycleRecord
    ) -> None:
        """Every axis's write (:meth:`_write_axes`), then one handshake bump if any was
        confirmed. The record gets every axis (multi-axis) and the first axis's fields."""
        comp = self.config.compensation
        self.handshake_token.new_cycle()
        await self._write_axes(aims, comp.on_disable)
        if any(axis.confirmed for axis in self.axes):
            problem = await self.handshake_token.bump()
            for axis, rec, _ in aims:
                if problem and axis.confirmed:
                    rec.write_status += f"; {problem}"
        first = aims[0][1]
        for name in _AXIS_FIELDS:
            setattr(record, name, getattr(first, name))
        if comp.axes is not None:
            record.axes = {rec.axis: rec for _, rec, _ in aims}

    async def _write_axes(
        self, aims: Sequence[tuple[Axis, AxisRecord, float | None]], on_disable: str
    ) -> None:
        """Read every axis's macro (one request), decide each, write the decided values
        (each guarded by its own read right before it: OPC UA one Read and one Write for
        every axis), read the written macros back (one request) and confirm each."""
        macros = [axis.macro for axis in self.axes]
        held = await read_each(self.cnc, macros)
        read_s = self.clock.now()
        decided: list[tuple[Axis, AxisRecord, Decision]] = []
        for axis, rec, aim in aims:
            decision = axis.decide(
                held[axis.macro], read_s, aim, rec, self.compensation_enabled, on_disable
            )
            if decision is not None:
                decided.append((axis, rec, decision))
        if not decided:
            return
        verdict = await self.handshake_token.check(macros)
        decided = [(a, r, d) for a, r, d in decided if a.may_write(verdict, r)]
        guarded = await write_each(self.cnc, [a.guarded_write(d) for a, _, d in decided])
        written = [(a, r, d) for a, r, d in decided if a.written(guarded[a.macro], r)]
        if written:
            read_back = await read_each(self.cnc, [axis.macro for axis, _, _ in written])
            for axis, rec, decision in written:
                axis.confirm(decision, read_back[axis.macro], rec)

    def _swap_promoted(self) -> None:
        """Between cycles: take a newly promoted (or rolled back) set into the bank.

        A store that cannot be read is logged and the models in use stay; a cycle
        never fails for it.
        """
        try:
            outcome = self.promotions.poll(self.bank)
        except Exception:
            log.exception(
                "%s: checking the promoted models failed; the models in use stay", self.config.id
            )
            return
        if outcome is None or not outcome.changed:
            return
        self.effects.set_models(self.bank.augmented())
        if self.online is not None:
            # The filter estimated the residual of the model that served until now; the
            # promoted model may well explain it (that is why it was proposed).
            self.online = OnlineCorrection(self.online.params)
            self._probe_basis = None
            log.info("%s: online correction restarts with the new models", self.config.id)

    def _deliver(self, record: CycleRecord) -> None:
        """Hand the record to every sink; a sink that raises is counted and logged, and
        neither stops the cycle nor keeps the other sinks from their record.

        The traceback is logged once when a sink starts failing, and one line when it
        works again, so a full disk does not flood the log every cycle.
        """
        for sink in self.sinks:
            name = sink_name(sink)
            try:
                sink(record)
            except Exception:
                self.sink_failures[name] = self.sink_failures.get(name, 0) + 1
                if name not in self._failing_sinks:
                    self._failing_sinks.add(name)
                    log.exception(
                        "%s: sink %s failed; the cycle goes on without it", self.config.id, name
                    )
                continue
            if name in self._failing_sinks:
                self._failing_sinks.discard(name)
                log.info(
                    "%s: sink %s works again (%d failure(s) so far)",
                    self.config.id,
                    name,
                    self.sink_failures[name],
                )

    async def _read_inputs(
        self, now: float
    ) -> tuple[dict[str, ChannelResult], float | None, list[str]]:
        bus_reads = [bus.read_all(now) for bus in self.buses]
        outcomes, speed = await read_together(bus_reads, self.cnc.read_speed())
        results: dict[str, ChannelResult] = {}
        failures: dict[str, str] = {}  # source → what failed
        for bus_config, outcome in zip(self.config.transmitters, outcomes, strict=True):
            if isinstance(outcome, BaseException):
                failures[f"bus {bus_config.name}"] = str(outcome)
                continue
            results.update(outcome)
            failures.update({f"sensor {r.sensor}": r.error for r in outcome.values() if r.error})
        speed_rpm = None
        if isinstance(speed, BaseException):
            failures["CNC"] = str(speed)
        elif math.isfinite(speed.actual_rpm):
            # A control that signs the speed by direction (M04, reverse) heats the bearings
            # as M03 does: the models, the regime rules and the log take its magnitude.
            speed_rpm = abs(float(speed.actual_rpm))
            if speed.actual_rpm < 0 and not self._reverse_noted:
                log.info(
                    "%s: the CNC reports a negative spindle speed (%g r/min, turning in "
                    "reverse); its magnitude is used",
                    self.config.id,
                    speed.actual_rpm,
                )
                self._reverse_noted = True
        else:
            failures["CNC"] = f"spindle speed is not a number ({speed.actual_rpm})"
        self._log_link_changes(failures)
        return results, speed_rpm, [f"{source}: {error}" for source, error in failures.items()]

    def _log_link_changes(self, failures: dict[str, str]) -> None:
        """Log a source's failure once when it starts and once when it clears, not every cycle."""
        for source in sorted(failures.keys() - self._link_down):
            log.error("%s: %s: %s", self.config.id, source, failures[source])
        for source in sorted(self._link_down - failures.keys()):
            log.info("%s: %s: recovered", self.config.id, source)
        self._link_down = set(failures)

    def _predict(self, banked: Banked | None, inputs: _Inputs) -> float | None:
        if banked is None:
            return None
        if isinstance(banked, BankedAugmented):
            return inputs.augmented_um[banked.model_id]  # stepped with this cycle's inputs
        sensors = tuple(banked.model.sensors_used_)
        rises = self.reference.rises_C(inputs.good_values, sensors)
        speed_rpm = inputs.speed_rpm
        if rises is None or (banked.model.uses_speed and speed_rpm is None):
            return None
        model_inputs = ModelInputs(
            rise_C=np.array([rises]),
            sensors=sensors,
            speed_rpm=np.array([speed_rpm if speed_rpm is not None else 0.0]),
        )
        value = float(banked.model.predict(model_inputs)[0])
        return value if math.isfinite(value) else None

    async def _write_alive(self, record: CycleRecord) -> None:
        """The next alive count in ``compensation.alive_macro``: the gateway runs and
        reaches this CNC (not: the compensation is good). Written in every cycle whose
        read of the compensation macro was answered, whatever the deadband, a hold or a
        switch-off decided.

        It comes after the compensation's write and read-back, so a slow or refused
        alive write never delays or replaces them. One plain write, no read-back: the
        CNC acts on no value of it, only on its change, and a count that did not land
        is exactly the stall a watchdog must see; the next cycle writes the next count
        anyway. The count advances only on an acknowledged write, so after a link drop
        the CNC gets the count after the last one it had, none invented meanwhile.
        """
        macro = self.config.compensation.alive_macro
        if macro is None or not any(axis.reached for axis in self.axes):
            return
        count = next_alive_count(self.alive)
        try:
            await self.cnc.write_macro(macro, float(count))
        except (CncError, ValueError) as exc:  # ValueError: a macro the driver cannot map
            self._machine_failed_writes += 1
            note = f"alive count not written to #{macro}: {exc}"
            record.write_status = "; ".join(filter(None, [record.write_status, note]))
            if not self._alive_failing:
                self._alive_failing = True
                log.warning("%s: %s (failed writes: %d)", self.config.id, note, self.failed_writes)
            return
        self.alive = count
        if self._alive_failing:
            self._alive_failing = False
            log.info("%s: alive count written to #%d again", self.config.id, macro)

    async def _read_probe(self, record: CycleRecord) -> None:
        """The CNC's probe macro (µm): a new value is a measurement of the real error."""
        macro = self.config.compensation.probe_macro
        if macro is None:
            return
        try:
            value = await self.cnc.read_macro(macro)
        except CncError:
            return  # the CNC link failure is already recorded for this cycle
        if math.isfinite(value) and value != self._last_probe_um:
            self._last_probe_um = value
            record.probe_error_um = value

    def _corrected(
        self, now: float, banked: Banked | None, predicted: float | None, record: AxisRecord
    ) -> float | None:
        """The prediction plus the online correction (bounded, decayed in silence); the
        interval widened by the variance the correction gained since the last probe.

        No prediction stays no prediction: the policy's hold-and-ramp path takes over.
        A model that stores its own online-correction noise model (``replay --store``)
        brings it along; the config's limits (bound, decay) always hold.
        """
        if self.online is None or predicted is None:
            return predicted
        params = self._online_params(banked)
        if params.kind != self.online.params.kind:
            log.info("%s: online correction restarts as %s", self.config.id, params.kind)
            self.online = OnlineCorrection(params)
        self.online.params = params
        record.correction_um = float(self.online.correction_at(now, predicted_um=predicted)[0])
        if record.interval_um is not None:
            record.interval_um = with_probe_age(
                record.interval_um,
                self.online.added_variance_um2(now, predicted_um=predicted),
                interval_nominal(banked),
            )
        return predicted + record.correction_um

    def _online_params(self, banked: Banked | None) -> CorrectionParams:
        limits = self.config.online_correction.params()
        document = banked.document if isinstance(banked, BankedAugmented) else None
        stored = (document or {}).get("online_correction") or {}
        return limits.with_noise_of(stored.get("params", {}))

    def _online_update(self, now: float, predicted: float | None, record: CycleRecord) -> None:
        """A new probe value updates the filter with the model's residual then (contracts §7):
        probe + compensation applied then − prediction then. The probe was measured since the
        last cycle, so "then" is the last cycle's prediction and applied value."""
        if self.online is None:
            return
        basis = self._probe_basis
        applied = record.applied_um
        self._probe_basis = None if predicted is None or applied is None else (predicted, applied)
        if record.probe_error_um is None or basis is None:
            return
        residual_um = record.probe_error_um + basis[1] - basis[0]
        outcome = self.online.update(now, residual_um, predicted_um=basis[0])
        record.probe_refused = not outcome.accepted
        if not outcome.accepted:
            log.warning(
                "%s: probe %.2f µm refused by the online correction (%s; refused so far: %d)",
                self.config.id,
                record.probe_error_um,
                outcome.reason,
                self.online.refused,
            )

    # --- running ------------------------------------------------------------------------
    async def run(
        self,
        stop: asyncio.Event | None = None,
        cycles: int | None = None,
        scheduler: CycleScheduler | None = None,
        phase_s: float = 0.0,
    ) -> None:
        """Cycle every ``cycle_s`` of machine time until ``stop`` is set or ``cycles`` ran.

        With a ``scheduler`` (the gateway's, shared by every machine) the loop waits on
        its one timer, and its cycles are due on the scheduler's grid for ``phase_s``
        (:meth:`CycleScheduler.next_due_s`), so the machines' polls are spread over the
        cycle and each slot's loops poll together; without one it sleeps on its own
        and starts at once. An overrun starts the next cycle at once, without catching
        up in a burst; the cycles after it are back on the grid.

        ``stop`` cuts the wait between cycles short, so a stop request is served at
        once whatever ``cycle_s`` is. A cycle in progress gets ``STOP_GRACE_S`` (wall)
        to finish its write and read-back; then it is cancelled. Nothing is lost by
        that: the policy moves its applied value only on a confirmed read-back, and
        the next start reads what the macro holds before it writes.
        """
        stop = stop or asyncio.Event()
        cycle_s = self.config.cycle_s
        if scheduler is not None:
            next_due = grid_due = scheduler.next_due_s(phase_s, cycle_s)
        else:
            next_due = grid_due = self.clock.now() + phase_s
        done = 0
        guard = _StopGuard(stop, self.config.id)
        try:
            while not stop.is_set() and (cycles is None or done < cycles):
                if scheduler is not None:
                    await scheduler.wait_until(next_due, stop)
                    if stop.is_set():
                        return
                self.due_s = next_due
                self.start_late_s = max(self.clock.now() - next_due, 0.0)
                if not await guard.cycle(self.run_cycle):
                    return
                done += 1
                now = self.clock.now()
                next_due, grid_due = after_cycle(grid_due, cycle_s, now)
                if next_due <= now:  # an overrun: at once
                    await asyncio.sleep(0)
                elif scheduler is None:
                    await self.clock.sleep(next_due - now, stop)
        finally:
            guard.close()

    async def close(self) -> None:
        self.effects.save()
        with contextlib.suppress(TimeoutError):  # a hung disk must not hang the stop
            async with asyncio.timeout(STATE_FLUSH_S):
                await self.effects.flush()
        for bus in self.buses:
            await bus.close()
        await self.cnc.close()


async def read_each(cnc: CncClient, macros: Sequence[int]) -> MacroReads:
    """Every macro's value or error, in one :meth:`CncClient.read_macros` call (one macro:
    :meth:`CncClient.read_macro`, the single-axis path as lean as it was); a failure of
    the whole call (the link) is every macro's error."""
    try:
        if len(macros) == 1:
            return {macros[0]: await cnc.read_macro(macros[0])}
        return await cnc.read_macros(macros)
    except CncError as exc:
        return dict.fromkeys(macros, exc)


async def write_each(cnc: CncClient, writes: Sequence[MacroWrite]) -> GuardedWrites:
    """Every guarded write's outcome, in one :meth:`CncClient.write_macros_if` call (one
    write: :meth:`CncClient.write_macro_if`, the single-axis path as lean as it was); a
    failure of the whole call (the link) is every macro's error."""
    try:
        if len(writes) == 1:
            (one,) = writes
            return {one.number: await cnc.write_macro_if(one.number, one.value, one.holds)}
        return await cnc.write_macros_if(writes) if writes else {}
    except CncError as exc:
        return {write.number: exc for write in writes}


async def read_together(
    bus_reads: Sequence[Awaitable[T]], speed_read: Awaitable[S]
) -> tuple[list[T | BaseException], S | BaseException]:
    """Await the reads concurrently, as ``gather(..., return_exceptions=True)`` does.

    The speed read runs in the calling task and only the bus reads get tasks of
    their own: one task fewer per machine and cycle than ``gather`` (which also
    adds a gathering future and its callbacks). The buses' outcomes come in the order
    given, then the speed's; an ``Exception`` is returned in its place, a cancellation
    cancels every read and propagates.
    """
    tasks = [asyncio.ensure_future(read) for read in bus_reads]
    try:
        try:
            speed: S | BaseException = await speed_read
        except Exception as exc:
            speed = exc
        outcomes: list[T | BaseException] = []
        for task in tasks:
            try:
                outcomes.append(await task)
            except Exception as exc:
                outcomes.append(exc)
    finally:
        for task in tasks:
            task.cancel()  # a no-op on the finished ones
    return outcomes, speed


class _StopGuard:
    """Gives a cycle in progress ``STOP_GRACE_S`` after a stop request, then cancels it.

    One watcher task per run of a loop instead of two futures per cycle: the cycle
    runs in the loop's own task, and the watcher cancels that task only while it is
    inside a cycle; :meth:`cycle` turns that one cancellation into "stopped".
    """

    def __init__(self, stop: asyncio.Event, machine: str) -> None:
        task = asyncio.current_task()
        assert task is not None, "a machine loop runs in a task"
        self._task = task
        self._machine = machine
        self._in_cycle = False
        self._cancelled = False
        self._watcher = asyncio.create_task(self._watch(stop))

    async def _watch(self, stop: asyncio.Event) -> None:
        await stop.wait()
        if not self._in_cycle:
            return  # between cycles: the loop sees the stop itself
        await asyncio.sleep(STOP_GRACE_S)
        if self._in_cycle:
            log.warning("%s: stop requested; cancelling the cycle in progress", self._machine)
            self._cancelled = True
            self._task.cancel()

    async def cycle(self, run_cycle: Callable[[], Awaitable[CycleRecord]]) -> bool:
        """Run one cycle; False when the stop's grace ran out and it was cancelled."""
        self._in_cycle = True
        try:
            await run_cycle()  # an exception of the cycle goes to the supervisor
        except asyncio.CancelledError:
            if self._cancelled:
                self._task.uncancel()
                return False
            raise
        finally:
            self._in_cycle = False
        return True

    def close(self) -> None:
        self._watcher.cancel()
