"""The main job on embedded defaults: simulate, fit, compensate, and show the gain.

1. Record training runs on the simulated machine (paper 002's six programmes:
   three speed spectra, three constant speeds), labelled by regime.
2. Fit models for each axis's error column (Z ``error_um``, X ``x_um``, Y ``y_um``):
   one per regime (``variable``, ``constant``), one on all runs, and one without
   each sensor (fallbacks for sensor faults).
3. Serve the machine over its protocols (Modbus TCP transmitters, an OPC UA
   CNC) and run the gateway's compensation loop against it on an accelerated
   clock, through a random production programme the fit never saw.
4. Report the thermal error at the tool with and without compensation, per
   axis. The "without" error is the machine's own growth along the axis over the
   same run (what the tool would see if the macro stayed at 0); the "with" error
   is growth minus the compensation the CNC applied to that axis.

The plant–loop pairing (:class:`simulator.closed_loop.ClosedLoop`) lives in the
simulator, so the integration tests step the same pairing cycle by cycle on a
manual clock without importing a harness from the product package.
"""

from __future__ import annotations

import csv
import math
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from drivers.clock import AcceleratedClock, Clock
from gateway.config import (
    GatewayConfig,
    LoggingSection,
    MachineSection,
    MonitorSection,
    OnlineCorrectionSection,
)
from gateway.demo.axis_table import axis_table
from gateway.live.loop import MachineLoop
from gateway.live.record import Sink
from gateway.outputs.sinks import Outputs
from gateway.wiring import build_buses, build_cnc, load_bank
from models.data.dataset import load_runs
from models.data.features import prepare
from models.fit.workflow import fit_and_store, fit_sensor_fallbacks
from models.online.correction import CorrectionParams
from models.store import ModelStore
from simulator.closed_loop import ClosedLoop, Trace
from simulator.params import load_params
from simulator.programs import program_by_name
from simulator.record import DEFAULT_PROGRAMS, record
from simulator.serve import SimulatedPlant, SimulatorConfig

#: The axes the demo compensates, in write order (the first is the primary axis).
DEMO_AXES: tuple[str, ...] = ("Z", "X", "Y")

TRAINING_REGIME = {
    name: ("constant" if name.startswith("const") else "variable") for name in DEFAULT_PROGRAMS
}


def write_training_data(path: Path, seed: int) -> None:
    """Record the six training programmes, with a ``regime`` column."""
    recording = record(load_params(), [program_by_name(n) for n in DEFAULT_PROGRAMS], seed=seed)
    lines = recording.to_csv().splitlines()
    rows = [lines[0] + ",regime"]
    rows += [f"{line},{TRAINING_REGIME[line.split(',', 1)[0]]}" for line in lines[1:]]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def axis_targets() -> dict[str, str]:
    """Each axis's error column in the simulated machine's recordings (Z: ``error_um``)."""
    params = load_params()
    return {"Z": "error_um", **{name: axis.column for name, axis in params.axes.items()}}


def axis_macros() -> dict[str, int]:
    """The macro through which the simulated CNC applies each axis's compensation."""
    params = load_params()
    return {
        "Z": params.compensation.macro,
        **{name: axis.compensation.macro for name, axis in params.axes.items()},
    }


def fit_models(
    training_csv: Path, store_dir: Path, version: str, targets: Sequence[str] = ("error_um",)
) -> list[str]:
    """Per error column: the per-regime models, the model of all runs, the sensor fallbacks."""
    store = ModelStore(store_dir)
    saved: dict[str, Path] = {}
    for target in targets:
        prepared = prepare(load_runs(training_csv, target=target))
        saved |= fit_and_store(
            prepared, "mlr", store, regime_column="regime", software_version=version
        ).saved
        saved |= fit_and_store(prepared, "mlr", store, software_version=version).saved
        saved |= fit_sensor_fallbacks(prepared, "mlr", store, software_version=version)
    return sorted(saved)


def machine_config(
    store_dir: Path,
    *,
    transmitters: list[dict[str, Any]],
    cnc: dict[str, Any],
    cycle_s: float,
    axes: Sequence[str] = ("Z",),
) -> MachineSection:
    """The demo machine: per-regime models with the whole-run model as fallback.

    ``("Z",)`` is the single-axis form (today's ``compensation.macro``); more axes give
    ``compensation.axes``, each with its own macro, error column and models.
    """
    write = {"unit": "mm", "clamp_um": 50.0, "slew_um_per_min": 20.0}
    regimes: dict[str, Any] = {"window_s": 1200, "constant_tolerance_rpm": 100, "min_dwell_s": 600}
    compensation: dict[str, Any] = dict(write)
    if tuple(axes) == ("Z",):
        compensation["macro"] = 500
        regimes |= axis_models("error_um")
    else:
        targets, macros = axis_targets(), axis_macros()
        compensation = {
            "axes": {
                axis: {"macro": macros[axis], "target": targets[axis], **write}
                | axis_models(targets[axis])
                for axis in axes
            }
        }
    return MachineSection.model_validate(
        {
            "id": "vmc-demo",
            "cycle_s": cycle_s,
            "transmitters": transmitters,
            "cnc": cnc,
            "compensation": compensation,
            "models": {"store": str(store_dir), "regimes": regimes},
        }
    )


def axis_models(target: str) -> dict[str, Any]:
    """The regime → model map and fallback of the models fitted for ``target``."""
    return {
        "models": {"variable": f"mlr-{target}-variable", "constant": f"mlr-{target}-constant"},
        "fallback_model": f"mlr-{target}-all",
    }


async def open_loop(
    plant: SimulatedPlant,
    machine: MachineSection,
    clock: Clock,
    sinks: Sequence[Sink] = (),
    state_dir: Path | None = None,
) -> ClosedLoop[MachineLoop]:
    await plant.start()
    loop = MachineLoop(
        machine,
        clock,
        build_buses(machine),
        build_cnc(machine, clock),
        load_bank(machine),
        state_dir=state_dir,
        sinks=sinks,
    )
    return ClosedLoop(plant, loop)


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def demo(
    workdir: Path,
    *,
    program: str = "production-7",
    seed: int = 1,
    speedup: float = 400.0,
    cycle_s: float = 15.0,
    version: str = "unknown",
    say: Any = print,
    effect: str | None = None,
    axes: Sequence[str] | None = None,
) -> dict[str, Any]:
    """The demo of the module docstring; with ``effect``, the machine hides that effect
    (the training runs do not have it, so the models lack it), and before the
    compensated run the residual monitor finds it and its proposal is promoted.

    ``axes``: the axes compensated (default :data:`DEMO_AXES`; Z alone with ``effect``,
    whose monitor and promotion serve the primary axis)."""
    if axes is None:
        axes = ("Z",) if effect is not None else DEMO_AXES
    workdir.mkdir(parents=True, exist_ok=True)
    training = workdir / "training.csv"
    store_dir = workdir / "models"
    steps = 5
    say(f"1/{steps} recording six training runs on the simulated machine → {training}")
    write_training_data(training, seed)
    targets = {axis: target for axis, target in axis_targets().items() if axis in axes}
    say(
        f"2/{steps} fitting models for {', '.join(f'{a} ({t})' for a, t in targets.items())}: "
        f"per regime, all runs, one without each sensor → {store_dir}"
    )
    _clear_store(store_dir)
    models = fit_models(training, store_dir, version, tuple(targets.values()))
    main_models = ", ".join(m for m in models if "without" not in m)
    say(f"    {len(models)} models: {main_models}, and one without each sensor")
    monitor_result = None
    if effect is not None:
        monitor_result = run_monitor_phase(store_dir, effect, seed, version, say, 3, steps)

    clock = AcceleratedClock(speedup)
    unseen = program_by_name(program)
    plant = _demo_plant(program, seed, effect, speedup, clock)
    machine = _demo_machine(plant, store_dir, cycle_s, effect, axes)
    hours = unseen.duration_s / 3600.0
    with_what = "" if effect is None else ", the promoted model and the online correction"
    say(
        f"{3 if effect is None else 4}/{steps} compensating {', '.join(axes)} through programme "
        f"'{program}' (not in the training data{with_what}, {hours:.1f} h of machine time at "
        f"×{speedup:g}: about {unseen.duration_s / speedup:.0f} s)"
    )
    closed = await _compensate(plant, machine, clock, workdir, unseen.duration_s)
    result: dict[str, Any] = dict(closed.trace.summary())
    result.update(
        {
            "program": program,
            "machine_hours": hours,
            "models": models,
            "regime_switches": [list(s) for s in closed.loop.selector.switches],
            "failed_writes": closed.loop.failed_writes,
            "models_used": sorted({r.model_id for r in closed.trace.records if r.model_id}),
            "axes_compensated": list(axes),
            "axes": closed.trace.axis_summary(),
        }
    )
    write_trace(workdir / "trace.csv", closed.trace)
    _say_errors(result, workdir, f"{4 if effect is None else 5}/{steps}", say)
    if effect is None:
        primary = store_dir
        if tuple(axes) != ("Z",):
            primary = _target_store(store_dir, targets["Z"], workdir / "models-z")
        monitor_result = run_monitor_phase(primary, None, seed, version, say, 5, steps)
    assert monitor_result is not None
    result["monitor"] = monitor_result
    for key in ("without_probes", "online_correction", "after_promotion"):
        if key in monitor_result:
            result[f"{key}_peak_um"] = monitor_result[key]["peak_um"]
            result[f"{key}_rmse_um"] = monitor_result[key]["rmse_um"]
    return result


def _clear_store(store_dir: Path) -> None:
    """A fresh model store every run: no model, proposal or version of an earlier demo."""
    for path in store_dir.glob("*.json"):
        path.unlink()
    for folder in ("augmented", "proposals", "versions"):
        shutil.rmtree(store_dir / folder, ignore_errors=True)


def _target_store(store_dir: Path, target: str, dest: Path) -> Path:
    """``dest``: a store of ``target``'s models alone (copies of the signed files).

    The residual monitor serves the primary axis, through a single-axis bank, which
    takes the models of one target.
    """
    dest.mkdir(parents=True, exist_ok=True)
    _clear_store(dest)
    for path in store_dir.glob(f"mlr-{target}-*.json"):
        shutil.copy2(path, dest / path.name)
    return dest


def _demo_plant(
    program: str, seed: int, effect: str | None, speedup: float, clock: AcceleratedClock
) -> SimulatedPlant:
    """The simulated machine the demo compensates: transmitters on Modbus TCP, CNC on OPC UA."""
    plant = SimulatedPlant(
        SimulatorConfig.model_validate(
            {
                "program": program,
                "seed": seed + 1000,
                "effects": [effect] if effect else [],
                "speedup": speedup,
                "publish_period_s": 0.02,
                "transmitters": {
                    "tcp": {
                        "port": free_port(),
                        "devices": [
                            {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
                            {"device_id": 2, "channels": ["T9", "ambient"]},
                        ],
                    }
                },
                "cnc": {"opcua": {"port": free_port()}},
            }
        ),
        clock=clock,
    )
    assert plant.tcp_transmitters is not None and plant.cnc_opcua is not None
    return plant


def _demo_machine(
    plant: SimulatedPlant,
    store_dir: Path,
    cycle_s: float,
    effect: str | None,
    axes: Sequence[str] = ("Z",),
) -> MachineSection:
    """The gateway's configuration of that machine, over its protocols."""
    assert plant.tcp_transmitters is not None and plant.cnc_opcua is not None
    host, port = plant.tcp_transmitters.address
    machine = machine_config(
        store_dir,
        transmitters=[
            {
                "name": "bus1",
                "tcp": {"host": host, "port": port},
                "devices": [
                    {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
                    {"device_id": 2, "channels": ["T9", None]},
                ],
            }
        ],
        cnc={"opcua": {"endpoint": plant.cnc_opcua.endpoint, "timeout_s": 2.0}},
        cycle_s=cycle_s,
        axes=axes,
    )
    if effect is None:
        return machine
    # The probe cycle and the online correction on, as in production.
    return machine.model_copy(
        update={
            "compensation": machine.compensation.model_copy(update={"probe_macro": 600}),
            "online_correction": OnlineCorrectionSection(enabled=True),
        }
    )


async def _compensate(
    plant: SimulatedPlant,
    machine: MachineSection,
    clock: AcceleratedClock,
    workdir: Path,
    duration_s: float,
) -> ClosedLoop[MachineLoop]:
    """Run the programme under compensation, logged as ``run`` logs, to its end."""
    # As on a real machine: the gateway is up and has its cold reference before the
    # operator presses cycle start (starting the servers takes minutes of machine time).
    plant.machine.schedule_program(float("inf"))
    # Logged as `run` logs, into the embedded local store (no server needed).
    outputs = Outputs(
        GatewayConfig(
            machines=[machine],
            state_dir=workdir / "state",
            logging=LoggingSection(local_store=workdir / "points.sqlite"),
        )
    )
    closed = await open_loop(plant, machine, clock, sinks=[outputs.sink])
    try:
        await closed.loop.run_cycle()
        plant.machine.schedule_program(plant.machine.time_s + machine.cycle_s)
        await closed.run_until(plant.machine.program_start_s + duration_s)
    finally:
        await closed.loop.close()
        await plant.stop()
        await outputs.stop()
    return closed


def _say_errors(result: dict[str, Any], workdir: Path, step: str, say: Any) -> None:
    """The thermal error at the tool with and without compensation, and where it is logged."""
    say(f"{step} thermal error at the tool in Z (µm), over the protocols:")
    for label, key in (
        ("without compensation", "uncompensated"),
        ("with compensation", "compensated"),
    ):
        peak, rmse = result[f"{key}_peak_um"], result[f"{key}_rmse_um"]
        say(f"    {label:22s} peak {peak:6.2f}   RMSE {rmse:6.2f}")
    say(f"    peak reduced by {result['reduction_pct']:.1f} % over {result['cycles']} cycles")
    say("    per axis, RMS and max |error| at the tool (µm):")
    for line in axis_table(result["axes"], result["axes_compensated"]):
        say(line)
    say(f"    per-cycle trace: {workdir / 'trace.csv'}")
    say(f"    every cycle logged to the local store {workdir / 'points.sqlite'}")


def run_monitor_phase(
    store_dir: Path, effect: str | None, seed: int, version: str, say: Any, step: int, steps: int
) -> dict[str, Any]:
    """The residual monitor over days of machine time (physics in-process), its proposal
    promoted as an operator would, and the next day without probes, with the online
    correction, and with the promoted model (peak and RMSE of each)."""
    from gateway.demo.monitor_phase import correction_note, monitor_phase

    hidden = effect or "no hidden effect"
    say(
        f"{step}/{steps} residual monitor: production days with {hidden}, a probe every 300 s "
        "(the machine's physics in-process, at CPU speed)"
    )
    result = monitor_phase(
        store_dir,
        effect,
        seed=seed,
        learn_days=3.0 if effect else 2.0,
        correction=OnlineCorrectionSection().params(),
        monitor_params=MonitorSection().params(),
        monitor_filter=CorrectionParams(process_um2_per_h=MonitorSection().process_um2_per_h),
        version=version,
        say=say,
    )
    say("    the next day (thermal error at the tool, µm):")
    for label, key in (
        ("without probes", "without_probes"),
        ("with online correction", "online_correction"),
        ("after promotion", "after_promotion"),
    ):
        if key in result:
            figures = result[key]
            say(f"    {label:22s} peak {figures['peak_um']:6.2f}   RMSE {figures['rmse_um']:6.2f}")
    for line in correction_note(result):
        say(line)
    return result


def write_trace(path: Path, trace: Trace) -> None:
    """One row per cycle; Z's columns first, then each other axis's pair
    (``uncompensated_x_um``, ``compensated_x_um``, …)."""
    others = [axis for axis in trace.axes_um if axis != "Z"]
    with path.open("w", newline="", encoding="utf-8") as out:
        writer = csv.writer(out)
        writer.writerow(
            [
                "time_s",
                "speed_rpm",
                "regime",
                "model_id",
                "predicted_um",
                "applied_um",
                "uncompensated_um",
                "compensated_um",
                "write_status",
                *(
                    f"{kind}_{axis.lower()}_um"
                    for axis in others
                    for kind in ("uncompensated", "compensated")
                ),
            ]
        )
        for k, (t, without, with_, rec) in enumerate(
            zip(
                trace.time_s,
                trace.uncompensated_um,
                trace.compensated_um,
                trace.records,
                strict=True,
            )
        ):
            writer.writerow(
                [
                    f"{t:.0f}",
                    "" if rec.speed_rpm is None else f"{rec.speed_rpm:.0f}",
                    rec.regime or "",
                    rec.model_id or "",
                    ""
                    if rec.predicted_um is None or math.isnan(rec.predicted_um)
                    else f"{rec.predicted_um:.2f}",
                    "" if rec.applied_um is None else f"{rec.applied_um:.2f}",
                    f"{without:.2f}",
                    f"{with_:.2f}",
                    rec.write_status,
                    *(f"{trace.axes_um[axis][i][k]:.2f}" for axis in others for i in (0, 1)),
                ]
            )
