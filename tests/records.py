"""Cycle records for tests and benchmarks of what consumes them (sinks, logging, SCADA)."""

from __future__ import annotations

from typing import Any

from gateway.live.record import CycleRecord


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
