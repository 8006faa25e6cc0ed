"""Cycle records for tests and benchmarks of what consumes them (sinks, logging, SCADA)."""

from __future__ import annotations

from typing import Any

from gateway.live.record import AxisRecord, CycleRecord


def written_record(
    machine: str,
    time_s: float,
    temperatures_C: dict[str, float | None],
    applied_um: float,
    **fields: Any,
) -> CycleRecord:
    """A cycle that wrote ``applied_um``: every sensor good, predicted = target = applied,
    the macro holding it in mm; ``fields`` override any other field of the record."""
    values: dict[str, Any] = {
        "quality": dict.fromkeys(temperatures_C, "good"),
        "quality_reasons": {},
        "speed_rpm": 4000.0,
        "regime": "variable",
        "model_id": "m",
        "predicted_um": applied_um,
        "target_um": applied_um,
        "written_cnc": applied_um / 1000.0,
        "write_status": "ok",
    }
    values.update(fields)
    return CycleRecord(
        machine=machine,
        time_s=time_s,
        temperatures_C=temperatures_C,
        applied_um=applied_um,
        **values,
    )


def axes_record(
    machine: str,
    time_s: float,
    temperatures_C: dict[str, float | None],
    applied_um: dict[str, float],
    **fields: Any,
) -> CycleRecord:
    """A cycle of a multi-axis machine that wrote ``applied_um[axis]`` on each axis (in
    the dict's order, the first the primary; axis ``A`` writes macro 500 + 2 × its index,
    model ``lag-ridge-<A>``, predicted = target = applied, half a micrometre of interval
    per index): the record's own per-axis fields repeat the first axis's, as the loop's
    do. ``fields`` override any other field of the record."""
    axes = {
        name: AxisRecord(
            axis=name,
            macro=500 + 2 * index,
            model_id=f"lag-ridge-{name}",
            predicted_um=value,
            target_um=value,
            applied_um=value,
            written_cnc=value / 1000.0,
            write_status="ok",
            interval_um=1.0 + 0.5 * index,
            training_span="inside",
        )
        for index, (name, value) in enumerate(applied_um.items())
    }
    first = next(iter(axes.values()))
    shared = {
        k: getattr(first, k)
        for k in ("model_id", "predicted_um", "target_um", "written_cnc", "write_status")
    }
    shared.update(interval_um=first.interval_um, training_span=first.training_span)
    shared.update(fields)
    record = written_record(machine, time_s, temperatures_C, first.applied_um or 0.0, **shared)
    record.axes = axes
    return record
