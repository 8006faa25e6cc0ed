"""The overview's live rows: what each machine's last cycle showed, and who is watching.

The gateway's sink (:meth:`LiveBoard.record`) only stores the cycle's record and
marks the machine changed: no formatting, no I/O, so a cycle is never delayed by
the browsers. A single ticker task (:meth:`LiveBoard.run`) turns the changed
machines into rows once per ``tick_s`` and encodes them once as a server-sent
event that every open overview receives; twenty browsers cost one encoding.
The rows are built and encoded ``SLICE`` machines at a time, handing the event
loop back between slices, so with hundreds of machines no cycle waits behind a
whole tick's work (one slice is a fraction of a millisecond); nothing is built
while no overview is open.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from gateway.live.record import CycleRecord

#: ``machine id → extra facts`` the gateway adds to a row (health counters, loop state).
Facts = Callable[[str], Mapping[str, Any]]

#: Machines turned into rows between two returns to the event loop.
SLICE = 16


def _num(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else round(float(value), 3)


@dataclass
class _Machine:
    record: CycleRecord | None = None
    probe_error_um: float | None = None
    probe_residual_um: float | None = None
    probe_time_s: float | None = None
    cnc_value: float | None = None  # the last value written and read back: what the CNC holds
    #: the same per axis of a multi-axis machine
    axis_cnc_values: dict[str, float] = field(default_factory=dict)


def _axis_rows(record: CycleRecord, state: _Machine) -> list[dict[str, Any]]:
    """Each axis of a multi-axis machine's cycle, in configured order ([] for one axis):
    what it predicted and applied, what its macro holds, and its write's outcome (a hold
    says why)."""
    return [
        {
            "axis": name,
            "macro": axis.macro,
            "model_id": axis.model_id,
            "predicted_um": _num(axis.predicted_um),
            "interval_um": _num(axis.interval_um),
            "applied_um": _num(axis.applied_um),
            "written_cnc": _num(state.axis_cnc_values.get(name)),
            "write_status": axis.write_status,
            "held": not axis.write_status.startswith("ok"),
            "uncertain": axis.uncertain,
            "training_span": axis.training_span,
        }
        for name, axis in record.axes.items()
    ]


@dataclass
class LiveBoard:
    """The last record of every machine, turned into overview rows on a timer."""

    machines: list[str]
    facts: Facts
    tick_s: float = 1.0
    _state: dict[str, _Machine] = field(default_factory=dict)
    _changed: set[str] = field(default_factory=set)
    _event: bytes = b""
    _serial: int = 0
    _news: asyncio.Condition | None = None
    _watchers: int = 0

    def __post_init__(self) -> None:
        self._state = {m: _Machine() for m in self.machines}

    def record(self, record: CycleRecord) -> None:
        """The gateway's sink: keep the record (and a probe's residual) for the next tick."""
        state = self._state.setdefault(record.machine, _Machine())
        state.record = record
        if record.written_cnc is not None:
            state.cnc_value = record.written_cnc
        for name, axis in record.axes.items():
            if axis.written_cnc is not None:
                state.axis_cnc_values[name] = axis.written_cnc
        if record.probe_error_um is not None and record.predicted_um is not None:
            state.probe_error_um = record.probe_error_um
            state.probe_residual_um = record.probe_error_um - record.predicted_um
            state.probe_time_s = time.time()
        self._changed.add(record.machine)

    def row(self, machine: str) -> dict[str, Any]:
        """What the overview shows of one machine (also the page's first render)."""
        state = self._state.get(machine) or _Machine()
        rec = state.record
        facts = dict(self.facts(machine))
        row: dict[str, Any] = {"machine": machine, **facts}
        if rec is None:
            return {**row, "sensors": [], "waiting": True}
        sensors = [
            {
                "name": name,
                "value_C": _num(value),
                "quality": rec.quality.get(name, "unknown"),
                "reason": rec.quality_reasons.get(name, ""),
            }
            for name, value in rec.temperatures_C.items()
        ]
        return {
            **row,
            "waiting": False,
            "regime": rec.regime,
            "model_id": rec.model_id,
            "speed_rpm": _num(rec.speed_rpm),
            "predicted_um": _num(rec.predicted_um),
            "interval_um": _num(rec.interval_um),
            "training_span": rec.training_span,
            "outside_inputs": list(rec.outside_inputs),
            "applied_um": _num(rec.applied_um),
            "correction_um": _num(rec.correction_um),
            "written_cnc": _num(state.cnc_value),
            "write_status": rec.write_status,
            "link_errors": len(rec.link_errors),
            "sensors": sensors,
            "probe_error_um": _num(state.probe_error_um),
            "probe_residual_um": _num(state.probe_residual_um),
            "axes": _axis_rows(rec, state),
        }

    def rows(self) -> list[dict[str, Any]]:
        return [self.row(m) for m in self._state]

    @property
    def serial(self) -> int:
        """The newest event's number: a new stream starts after it (its page has the rows)."""
        return self._serial

    async def run(self, stop: asyncio.Event) -> None:
        """Every ``tick_s``: encode the changed machines' rows once and wake the watchers."""
        self._news = asyncio.Condition()
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), self.tick_s)
            if not self._changed or not self._watchers:
                continue
            changed, self._changed = sorted(self._changed), set()
            parts = []
            for start in range(0, len(changed), SLICE):
                rows = [self.row(m) for m in changed[start : start + SLICE]]
                parts.append(json.dumps(rows, separators=(",", ":"))[1:-1])
                await asyncio.sleep(0)  # let the cycles due meanwhile run
            self._serial += 1
            payload = ",".join(parts)
            self._event = f"id: {self._serial}\nevent: rows\ndata: [{payload}]\n\n".encode()
            async with self._news:
                self._news.notify_all()

    async def next_event(self, after: int) -> tuple[int, bytes]:
        """Wait for an event newer than ``after``; (its serial, its bytes)."""
        if self._news is None:
            raise RuntimeError("the board's ticker is not running")
        self._watchers += 1
        try:
            async with self._news:
                await self._news.wait_for(lambda: self._serial > after)
                return self._serial, self._event
        finally:
            self._watchers -= 1
