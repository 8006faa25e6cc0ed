"""The simulated machine: thermal network + sensors + programme + CNC, one object.

It advances on a fixed grid of ``sub_step_s`` seconds of machine time
(``advance_to``), and is what the protocol endpoints publish (``snapshot``) and
write to (``write_macro``, see :mod:`simulator.link`). Closed loop: the value a
client writes to the compensation macro (default #500, in mm) shifts the tool,
so the measured error is

    error = Z growth − sign · #500 · (µm per CNC unit) + probe noise,

and the same per X/Y axis (``axes`` in machine.yaml, :mod:`simulator.axes`): that
axis's growth minus its own compensation macro (#502 for X, #504 for Y by default).

With ``ageing`` (machine.yaml) the Z growth also drifts over machine days: the
bearing's share scaled by 1 + preload_gain_per_day · days, plus
coolant_offset_um_per_day · days. Both are off (0) by default, and then the
growth is computed exactly as without them (a recording keeps its bytes).

All randomness (sensor and probe noise) is a function of the seed, the machine
time and the channel (:mod:`simulator.noise`), never of how often or when (in
wall-clock time) the machine is read: a recording is reproducible to the byte,
and a served machine gives the same readings at the same machine time however
its publishes fall.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from simulator.axes import AxisFaces
from simulator.effects import HiddenEffects
from simulator.faults import SensorFault
from simulator.link import (
    MACRO_FIRST,
    MACRO_LAST,
    ChannelReading,
    MachineSnapshot,
    RunMode,
    check_macro_number,
)
from simulator.noise import PROBE, SENSORS, MachineNoise, axis_probe_stream
from simulator.params import NODES, Compensation, MachineParams
from simulator.programs import SpeedProgram
from simulator.thermal import ThermalNetwork

AMBIENT_CHANNEL = "ambient"


class SimulatedMachine:
    def __init__(
        self,
        params: MachineParams,
        program: SpeedProgram,
        effects: Iterable[str] = (),
        seed: int = 0,
        start_s: float = 0.0,
    ) -> None:
        self.params = params
        self.program = program
        self.effects = HiddenEffects(params, effects)
        self.network = ThermalNetwork(
            params, params.sub_step_s, self.effects.coolant_conductance_W_per_K
        )
        self.noise = MachineNoise(seed)
        self.program_start_s = start_s
        self.created_s = start_s
        self.time_s = start_s
        self.reference_C = params.ambient_C
        self.nodes_C = np.full(len(NODES), params.ambient_C)
        self.sensor_names = tuple(params.sensors)
        self.mix = np.array([[s.mix.get(n, 0.0) for n in NODES] for s in params.sensors.values()])
        self.offsets_C = np.array([s.offset_C for s in params.sensors.values()])
        self.sensor_decay = np.exp(
            -params.sub_step_s / np.array([s.lag_s for s in params.sensors.values()])
        )
        self.sensors_C = self.mix @ self.nodes_C
        self.ambient_decay = math.exp(-params.sub_step_s / params.ambient_sensor.lag_s)
        self.ambient_sensor_C = params.ambient_C
        self.faces = AxisFaces(params.axes, params.sub_step_s, params.ambient_C)
        self.macros: dict[int, float] = dict.fromkeys(range(MACRO_FIRST, MACRO_LAST + 1), 0.0)
        self.faults: list[SensorFault] = []
        self.probe_error_um: float | None = None
        self._next_probe_s = start_s + params.probe.period_s
        self.compensation_log: list[tuple[float, float]] = []

    # --- time -------------------------------------------------------------------------
    def schedule_program(self, start_s: float) -> None:
        """Press cycle start at machine time ``start_s``; until then the spindle rests."""
        if start_s < self.time_s:
            raise ValueError(f"cannot start the programme in the past ({start_s} < {self.time_s})")
        self.program_start_s = start_s

    @property
    def run_time_s(self) -> float:
        return self.time_s - self.program_start_s

    def commanded_speed_rpm(self, time_s: float | None = None) -> float:
        t = self.time_s if time_s is None else time_s
        return self.program.speed_at(t - self.program_start_s)

    def advance_to(self, time_s: float) -> None:
        """Integrate up to ``time_s`` in whole sub-steps (state time never runs ahead)."""
        h = self.params.sub_step_s
        while self.time_s + h <= time_s + 1e-9:
            self._step(h)

    def _step(self, h: float) -> None:
        speed = self.commanded_speed_rpm()
        room = self.effects.room_C(self.time_s)
        coolant = self.effects.coolant_C(self.time_s, self.params.ambient_C)
        # The hall air reaches the column; the spindle head sees the enclosure air.
        air = np.full(len(NODES), self.params.ambient_C)
        air[NODES.index("column")] = room
        self.nodes_C = self.network.step(self.nodes_C, speed, air, coolant)
        self.effects.advance_lag(self.nodes_C[NODES.index("shaft")], h)
        self.faces.step(self.nodes_C)
        self.sensors_C = self.sensor_decay * self.sensors_C + (1 - self.sensor_decay) * (
            self.mix @ self.nodes_C
        )
        self.ambient_sensor_C = (
            self.ambient_decay * self.ambient_sensor_C + (1 - self.ambient_decay) * room
        )
        self.time_s += h
        self._hold_stuck_sensors()
        if self.time_s + 1e-9 >= self._next_probe_s:
            self._next_probe_s += self.params.probe.period_s
            self.probe_error_um = self.measured_error_um()
            self.macros[self.params.probe.macro] = self.probe_error_um
            for name, axis in self.params.axes.items():
                self.macros[axis.probe_macro] = self.axis_measured_error_um(name)

    # --- physics read-outs ------------------------------------------------------------
    def growth_um(self) -> float:
        """Z thermal growth (µm, positive = tool towards the table), before compensation."""
        rise = {n: self.nodes_C[i] - self.reference_C for i, n in enumerate(NODES)}
        total = 0.0
        ageing = self.params.ageing
        for node, um_per_K in self.params.growth_um_per_K.items():
            if node == "bearing" and ageing.preload_gain_per_day != 0.0:
                total += um_per_K * rise[node] * self.preload_factor()
            elif node == "shaft":
                total += self.effects.shaft_growth_um(
                    self.nodes_C[NODES.index("shaft")], self.reference_C, um_per_K
                )
            else:
                total += um_per_K * rise[node]
        if ageing.coolant_offset_um_per_day != 0.0:
            total += ageing.coolant_offset_um_per_day * self.age_days
        return total + self.effects.direct_um(self.commanded_speed_rpm(), self.run_time_s)

    # --- ageing -----------------------------------------------------------------------
    @property
    def age_days(self) -> float:
        """Machine age in days of machine time (``ageing.start_days`` at creation)."""
        return self.params.ageing.start_days + (self.time_s - self.created_s) / 86400.0

    def preload_factor(self) -> float:
        """How much the bearing's Z growth is scaled by the drifting preload now."""
        return 1.0 + self.params.ageing.preload_gain_per_day * self.age_days

    def applied_compensation_um(self) -> float:
        return self._applied_um(self.params.compensation)

    def _applied_um(self, comp: Compensation) -> float:
        return comp.sign * self.macros[comp.macro] * comp.um_per_unit

    # --- X and Y ----------------------------------------------------------------------
    def axis_growth_um(self, axis: str) -> float:
        """Growth along ``axis`` (µm) before compensation; ``Z`` is :meth:`growth_um`."""
        if axis == "Z":
            return self.growth_um()
        return self.faces.growth_um()[self._axis(axis)]

    def axis_true_error_um(self, axis: str) -> float:
        """Error along ``axis`` at the tool after that axis's compensation, without noise."""
        if axis == "Z":
            return self.true_error_um()
        return self.axis_growth_um(axis) - self._applied_um(self.params.axes[axis].compensation)

    def axis_measured_error_um(self, axis: str) -> float:
        """What the probe measures along ``axis``: its true error plus its own probe noise."""
        if axis == "Z":
            return self.measured_error_um()
        noise = self.noise.normal(axis_probe_stream(axis), self.sample_index, 1)[0]
        return self.axis_true_error_um(axis) + float(noise) * self.params.probe.noise_um

    @property
    def axis_names(self) -> tuple[str, ...]:
        """Every axis with a growth: Z, then the X/Y axes of the parameters in order."""
        return ("Z", *self.params.axes)

    def _axis(self, axis: str) -> str:
        if axis not in self.params.axes:
            raise ValueError(f"no axis '{axis}' (axes: {', '.join(self.axis_names)})")
        return axis

    def true_error_um(self) -> float:
        """Error at the tool after the CNC applied the compensation, without probe noise."""
        return self.growth_um() - self.applied_compensation_um()

    def measured_error_um(self) -> float:
        """What a probe measures: the true error plus probe noise (fixed by machine time)."""
        noise = self.noise.normal(PROBE, self.sample_index, 1)[0]
        return self.true_error_um() + float(noise) * self.params.probe.noise_um

    @property
    def sample_index(self) -> int:
        """Machine time in sub-steps: what the noise of a reading is keyed on."""
        return round(self.time_s / self.params.sub_step_s)

    # --- sensors ------------------------------------------------------------------------
    def add_fault(self, fault: SensorFault) -> None:
        if fault.sensor not in (*self.sensor_names, AMBIENT_CHANNEL):
            raise ValueError(
                f"no sensor '{fault.sensor}' (sensors: {', '.join(self.sensor_names)})"
            )
        self.faults.append(fault)
        self._hold_stuck_sensors()

    def _hold_stuck_sensors(self) -> None:
        """A stuck sensor freezes at its reading of the machine time the fault starts.

        Taken here (at the first sub-step of the fault, or when a fault already
        under way is added), not at whichever read happens to come first.
        """
        stuck = [f for f in self.faults if f.kind == "stuck" and f.active(self.time_s)]
        if any(f.held_C is None for f in stuck):
            clean = self._clean_readings()
            for fault in stuck:
                if fault.held_C is None:
                    fault.hold(clean[fault.sensor].value_C)

    def clear_faults(self) -> None:
        self.faults.clear()

    def readings(self) -> dict[str, ChannelReading]:
        """What each transmitter channel measures now (°C), with noise and faults."""
        readings = self._clean_readings()
        for fault in self.faults:
            readings[fault.sensor] = fault.apply(readings[fault.sensor], self.time_s)
        return readings

    def _clean_readings(self) -> dict[str, ChannelReading]:
        """Every channel with its noise at this machine time, before faults."""
        draws = self.noise.normal(SENSORS, self.sample_index, len(self.sensor_names) + 1)
        noise = draws * self.params.sensor_noise_C
        values = self.sensors_C + self.offsets_C + noise[:-1]
        readings = {
            name: ChannelReading(float(v))
            for name, v in zip(self.sensor_names, values, strict=True)
        }
        readings[AMBIENT_CHANNEL] = ChannelReading(float(self.ambient_sensor_C + noise[-1]))
        return readings

    # --- MachineLink --------------------------------------------------------------------
    def snapshot(self) -> MachineSnapshot:
        in_program = 0 <= self.run_time_s < self.program.duration_s
        speed = self.commanded_speed_rpm()
        return MachineSnapshot(
            time_s=self.time_s,
            channels=self.readings(),
            actual_speed_rpm=speed,
            commanded_speed_rpm=speed,
            run_mode=RunMode.AUTO if in_program else RunMode.STOP,
            macros=dict(self.macros),
            probe_error_um=self.probe_error_um,
        )

    def write_macro(self, number: int, value: float) -> None:
        check_macro_number(number)
        if not math.isfinite(value):
            raise ValueError(f"macro #{number}: a finite value was expected, got {value}")
        self.macros[number] = float(value)
        if number == self.params.compensation.macro:
            self.compensation_log.append((self.time_s, float(value)))
