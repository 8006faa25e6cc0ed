"""Offline recording: run the machine through programmes and write measured runs.

No servers, as fast as the CPU allows. Each programme is one run on a machine
that starts cold (at room temperature), with ``time_s`` from 0, as separate
test days would be. Like a real thermal test, every run opens with
``REST_BEFORE_S`` (10 min) at rest, the spindle stopped, before the programme
starts: the readings the probe is zeroed on. Rows are sampled every
``sample_s`` seconds; temperatures are written at the transmitters' register
resolution (0.1 °C) and the error at 0.01 µm. The same seed gives the same bytes.

The Z error is ``error_um``; each X/Y axis of the parameters adds its own error
column after it (``x_um``, ``y_um`` by default), measured by the same probe.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from simulator.effects import parse_effects
from simulator.machine import AMBIENT_CHANNEL, SimulatedMachine
from simulator.params import MachineParams
from simulator.programs import SpeedProgram

REST_BEFORE_S = 600.0
DEFAULT_PROGRAMS = (
    "iso230-spectrum",
    "spectrum-swapped",
    "spectrum-const4000",
    "const2000",
    "const4000",
    "const6000",
)


@dataclass(frozen=True)
class Recording:
    header: tuple[str, ...]
    rows: list[tuple]

    def to_csv(self) -> str:
        out = io.StringIO()
        out.write(",".join(self.header) + "\n")
        for row in self.rows:
            errors = len(self.header) - self.header.index("error_um")
            run, time_s, speed, *temps = row[:-errors]
            *temps, ambient = temps
            cells = [
                run,
                f"{time_s:.0f}",
                f"{speed:.0f}",
                *(f"{t:.1f}" for t in temps),
                f"{ambient:.1f}",
                *(f"{error:.2f}" for error in row[-errors:]),
            ]
            out.write(",".join(cells) + "\n")
        return out.getvalue()


def run_ids(programs: Sequence[SpeedProgram]) -> list[str]:
    """Programme names, numbered when one appears more than once."""
    counts: dict[str, int] = {}
    ids = []
    for program in programs:
        counts[program.name] = counts.get(program.name, 0) + 1
        ids.append(
            program.name if counts[program.name] == 1 else f"{program.name}#{counts[program.name]}"
        )
    return ids


def record(
    params: MachineParams,
    programs: Sequence[SpeedProgram],
    effects: Sequence[str] = (),
    seed: int = 0,
    sample_s: float = 60.0,
) -> Recording:
    active = parse_effects(effects)
    if (
        sample_s < params.sub_step_s
        or abs(sample_s / params.sub_step_s - round(sample_s / params.sub_step_s)) > 1e-9
    ):
        raise ValueError(
            f"sample_s must be a whole multiple of the sub-step ({params.sub_step_s:g} s)"
        )
    seeds = np.random.SeedSequence(seed).spawn(len(programs))
    sensors = tuple(params.sensors)
    axes = tuple(params.axes)
    errors = ("error_um", *(params.axes[a].column for a in axes))
    header = ("run", "time_s", "speed_rpm", *sensors, "ambient_C", *errors)
    rows: list[tuple] = []
    for run, programme, child in zip(run_ids(programs), programs, seeds, strict=True):
        program = SpeedProgram(programme.name, ((REST_BEFORE_S, 0.0), *programme.segments))
        machine = SimulatedMachine(params, program, active, seed=int(child.generate_state(1)[0]))
        steps = int(program.duration_s // sample_s)
        for k in range(steps + 1):
            machine.advance_to(k * sample_s)
            readings = machine.readings()
            rows.append(
                (
                    run,
                    machine.time_s,
                    machine.commanded_speed_rpm(),
                    *(readings[name].value_C for name in sensors),
                    readings[AMBIENT_CHANNEL].value_C,
                    machine.measured_error_um(),
                    *(machine.axis_measured_error_um(a) for a in axes),
                )
            )
    return Recording(header, rows)


def write_recording(path: Path, recording: Recording) -> None:
    path.write_text(recording.to_csv(), encoding="utf-8", newline="")
