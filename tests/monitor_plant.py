"""The simulated machine's physics and a model, cycle by cycle in-process, as cycle records.

For the long runs of the residual monitor's tests (days of machine time): the
physics of :class:`simulator.machine.SimulatedMachine` advanced cycle by cycle,
the demo's fitted model predicting from the temperature rises above the first
cycle's readings, the prediction applied to the CNC's macro (the machine's own
compensation path, not the gateway's slew limit), and the probe cycle's value
read as the runtime reads it. Each cycle becomes a :class:`gateway.runtime.CycleRecord`
handed to the sinks. The protocol path is tested end to end in
``tests/test_monitor_loop.py``; this is its physics at CPU speed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gateway.model_bank import ModelBank
from gateway.runtime import CycleRecord
from models.base import ModelInputs
from models.effect_stream import StreamingAugmented
from simulator.machine import SimulatedMachine
from simulator.params import load_params
from simulator.programs import SpeedProgram

SENSORS = tuple(f"T{i}" for i in range(1, 10))
PLAIN_MODEL = "mlr-error_um-all"


@dataclass
class InProcessPlant:
    store: Path
    program: SpeedProgram
    effects: tuple[str, ...] = ()
    seed: int = 0
    cycle_s: float = 15.0
    probe_period_s: float = 300.0
    sinks: list[Callable[[CycleRecord], None]] = field(default_factory=list)
    errors_um: list[float] = field(default_factory=list)  # compensated error at the tool

    def __post_init__(self) -> None:
        params = load_params()
        params = params.model_copy(
            update={"probe": params.probe.model_copy(update={"period_s": self.probe_period_s})}
        )
        self.machine = SimulatedMachine(params, self.program, self.effects, seed=self.seed)
        self.model = ModelBank.from_store(self.store).get(PLAIN_MODEL).model  # type: ignore[union-attr]
        self.stream: StreamingAugmented | None = None
        self.reference_C: dict[str, float] | None = None
        self.time_s = 0.0
        self._last_probe: float | None = None
        self.records = 0
        self._rows: list[tuple[float, dict[str, float], float]] = []  # for warming a stream

    def promote(self, document: dict[str, Any]) -> None:
        """Use an augmented model from now on; its states warmed on the cycles so far."""
        stream = StreamingAugmented(document)
        for time_s, rises, speed in self._rows:
            stream.step(time_s, rises, speed)
        self.stream = stream

    def predict(self, rises: dict[str, float], speed: float) -> float:
        if self.stream is not None:
            value = self.stream.step(self.time_s, rises, speed)
            return float("nan") if value is None else value
        inputs = ModelInputs(
            rise_C=np.array([[rises[s] for s in self.model.sensors_used_]]),
            sensors=tuple(self.model.sensors_used_),
            speed_rpm=np.array([speed]),
        )
        return float(self.model.predict(inputs)[0])

    def cycle(self) -> CycleRecord:
        self.time_s += self.cycle_s
        machine = self.machine
        machine.advance_to(self.time_s)
        readings = machine.readings()
        temps = {s: round(readings[s].value_C, 1) for s in SENSORS}
        if self.reference_C is None:
            self.reference_C = dict(temps)
        rises = {s: temps[s] - self.reference_C[s] for s in SENSORS}
        speed = machine.commanded_speed_rpm()
        self._rows.append((self.time_s, rises, speed))
        predicted = self.predict(rises, speed)
        applied = predicted if np.isfinite(predicted) else 0.0
        comp = machine.params.compensation
        machine.write_macro(comp.macro, applied / comp.um_per_unit / comp.sign)
        self.errors_um.append(machine.true_error_um())
        probe = machine.macros[machine.params.probe.macro]
        new_probe = None
        if machine.probe_error_um is not None and probe != self._last_probe:
            self._last_probe = probe
            new_probe = probe
        record = CycleRecord(
            machine="in-process",
            time_s=self.time_s,
            temperatures_C=dict(temps),
            quality=dict.fromkeys(SENSORS, "good"),
            quality_reasons={},
            speed_rpm=speed,
            regime=None,
            model_id=PLAIN_MODEL,
            predicted_um=predicted if np.isfinite(predicted) else None,
            target_um=applied,
            applied_um=applied,
            written_cnc=None,
            write_status="ok",
            probe_error_um=new_probe,
        )
        for sink in self.sinks:
            sink(record)
        self.records += 1
        return record

    def run_for(self, duration_s: float, until: Callable[[], bool] | None = None) -> float:
        """Cycles for ``duration_s`` (or until ``until()``); the machine time it took."""
        start = self.time_s
        while self.time_s - start < duration_s:
            self.cycle()
            if until is not None and until():
                break
        return self.time_s - start

    def rmse_um(self, last: int | None = None) -> float:
        errors = np.asarray(self.errors_um if last is None else self.errors_um[-last:])
        return float(np.sqrt(np.mean(errors**2)))


def programme_days(seed: int, days: int) -> SpeedProgram:
    """``days`` random job-shop days back to back, each with its cool-down (one programme)."""
    from simulator.programs import production_program

    segments: list[tuple[float, float]] = [(600.0, 0.0)]
    for day in range(days):
        segments += production_program(seed * 1000 + day, 14 * 3600.0).segments
        segments.append((24 * 3600.0 - 14 * 3600.0 - 7200.0, 0.0))  # the night at rest
    return SpeedProgram(f"days-{seed}", tuple(segments))


def sinks_of(*sinks: Callable[[CycleRecord], None]) -> Sequence[Callable[[CycleRecord], None]]:
    return list(sinks)
