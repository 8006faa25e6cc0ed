"""Time-series points from compensation cycles (the :class:`Point` type).

Every :class:`~gateway.live.loop.CycleRecord` becomes:

* one ``spindle_cycle`` point — tags ``machine`` (+ ``regime``, ``model_id`` when
  known; for a machine with several axes, see below); fields ``speed_rpm``,
  ``predicted_um``, ``target_um``, ``applied_um``,
  ``written_cnc`` (the value written to the CNC macro, in the CNC's unit),
  ``interval_um`` (half-width of the calibrated interval around ``predicted_um``, when
  known), ``training_span`` (text: inside / outside) with ``outside_inputs`` (text: the
  inputs outside the model's training span, comma-separated; absent when inside),
  ``write_status`` (text) and ``link_errors`` (how many sources failed);
* one ``spindle_temperature`` point per sensor — tags ``machine``, ``sensor``,
  ``quality``; field ``value_C``, and for a sensor that is not good, field ``reason``
  (text: "transmitter fault code 1 (open circuit)", "stale", …).

A machine configured with several axes (``compensation.axes``: its record carries
:attr:`~gateway.live.record.CycleRecord.axes`) gets one ``spindle_cycle`` point per axis
instead of one, in the configured order, each with the extra tag ``axis`` (the axis
name: X, Y, Z, ...), that axis's ``model_id`` tag and that axis's fields; ``speed_rpm``
and ``link_errors`` (the cycle's) are on every axis's point, the temperature points
come once per cycle as for one axis. A point without an ``axis`` tag is the single
axis of a machine without ``compensation.axes``.

A measured thermal error (a probe or dial-gauge reading) is a ``spindle_probe``
point with field ``error_um`` (:func:`probe_point`).

Units are part of the field names (µm, °C, r/min). A value the cycle did not have
(``None``) or that is not a finite number is omitted, never written as 0: a
good sensor without a value gets no temperature point, a sensor that is not good
gets one with its ``reason`` only. An open circuit has no value for as long as it
lasts, so without that point the log (and the console's event table, which reads
the quality flips from it) would not show the sensor going bad. Float fields are always
written as floats, so a whole number never turns a float field into an integer
one (InfluxDB refuses a field whose type changes).

Timestamps: ``time_ns = round((epoch_s + t) × 1e9)``, where ``t`` is the record's
stamp (:attr:`~gateway.live.record.CycleRecord.stamped_s`: in the plant the wall time
of the cycle's start, the time every output gives the cycle; else its machine time)
and ``epoch_s`` the real time (Unix seconds) that time 0 stands for. Two points are
the same point when measurement, tags and ``time_ns`` agree (InfluxDB's identity),
which is what makes re-sending safe.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from gateway.live.record import AxisRecord, CycleRecord

CYCLE_MEASUREMENT = "spindle_cycle"
TEMPERATURE_MEASUREMENT = "spindle_temperature"
PROBE_MEASUREMENT = "spindle_probe"

FieldValue = float | int | str | bool
NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class Point:
    """One time-series point: what InfluxDB stores as measurement, tags, fields, time.

    A field may be None only in the Sparkplug node's backlog, where a metric without a
    value travels as a null; the cycle's points for InfluxDB and the local store leave
    such a field out.
    """

    measurement: str
    tags: dict[str, str]
    fields: Mapping[str, FieldValue | None]
    time_ns: int

    @property
    def machine(self) -> str | None:
        return self.tags.get("machine")

    @property
    def time_s(self) -> float:
        """Unix seconds (subtract the ``epoch_s`` used to make the point for machine time)."""
        return self.time_ns / NS_PER_S

    def series_key(self) -> tuple[str, tuple[tuple[str, str], ...]]:
        """Measurement and sorted tags: with ``time_ns``, the identity of the point."""
        return self.measurement, tuple(sorted(self.tags.items()))

    def to_json(self) -> dict:
        return {"m": self.measurement, "t": self.tags, "f": self.fields, "ns": self.time_ns}

    @classmethod
    def from_json(cls, data: Mapping) -> Point:
        return cls(
            measurement=str(data["m"]),
            tags={str(k): str(v) for k, v in data["t"].items()},
            fields=dict(data["f"]),
            time_ns=int(data["ns"]),
        )


def to_time_ns(time_s: float, epoch_s: float = 0.0) -> int:
    """Nanoseconds since the Unix epoch of machine time ``time_s``."""
    return round((epoch_s + time_s) * NS_PER_S)


def _float(value: float | None) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _floats(**values: float | None) -> dict[str, FieldValue]:
    return {k: v for k, v in ((k, _float(v)) for k, v in values.items()) if v is not None}


def _cycle_point(
    record: CycleRecord, outcome: CycleRecord | AxisRecord, axis: str | None, time_ns: int
) -> Point:
    """A ``spindle_cycle`` point of the cycle with ``outcome``'s model and values (the
    record's own, or one axis's, tagged ``axis``)."""
    tags = {"machine": record.machine}
    if record.regime:
        tags["regime"] = record.regime
    if axis is not None:
        tags["axis"] = axis
    if outcome.model_id:
        tags["model_id"] = outcome.model_id
    fields = _floats(
        speed_rpm=record.speed_rpm,
        predicted_um=outcome.predicted_um,
        target_um=outcome.target_um,
        applied_um=outcome.applied_um,
        written_cnc=outcome.written_cnc,
        correction_um=outcome.correction_um,
        interval_um=outcome.interval_um,
    )
    if outcome.training_span is not None:
        fields["training_span"] = outcome.training_span
    if outcome.outside_inputs:  # InfluxDB keeps no empty string field: none when inside
        fields["outside_inputs"] = ",".join(outcome.outside_inputs)
    fields["write_status"] = outcome.write_status
    fields["link_errors"] = len(record.link_errors)
    return Point(CYCLE_MEASUREMENT, tags, fields, time_ns)


def points_from_record(record: CycleRecord, epoch_s: float = 0.0) -> list[Point]:
    """The points of one cycle: its ``spindle_cycle`` point (one per axis, tagged
    ``axis``, for a multi-axis record), then one per sensor that has a value or is not
    good."""
    time_ns = to_time_ns(record.stamped_s, epoch_s)
    if record.axes:
        points = [_cycle_point(record, a, name, time_ns) for name, a in record.axes.items()]
    else:
        points = [_cycle_point(record, record, None, time_ns)]
    for sensor, value in record.temperatures_C.items():
        quality = record.quality.get(sensor, "unknown")
        value_C = _float(value)
        sensor_fields: dict[str, FieldValue] = {} if value_C is None else {"value_C": value_C}
        if quality != "good":
            sensor_fields["reason"] = record.quality_reasons.get(sensor) or quality
        elif value_C is None:
            continue
        sensor_tags = {"machine": record.machine, "sensor": sensor, "quality": quality}
        points.append(Point(TEMPERATURE_MEASUREMENT, sensor_tags, sensor_fields, time_ns))
    return points


def probe_point(machine: str, time_s: float, error_um: float, epoch_s: float = 0.0) -> Point:
    """A measured thermal error (µm) of ``machine`` at machine time ``time_s``."""
    value = _float(error_um)
    if value is None:
        raise ValueError(f"error_um must be a finite number, got {error_um!r}")
    return Point(
        PROBE_MEASUREMENT, {"machine": machine}, {"error_um": value}, to_time_ns(time_s, epoch_s)
    )


def record_sink(
    write: Callable[[list[Point]], object], epoch_s: float = 0.0
) -> Callable[[CycleRecord], None]:
    """A :data:`gateway.live.loop.Sink` that turns each record into points and hands them on.

    ``write`` is e.g. :meth:`gateway.outputs.disk_buffer.PointBuffer.append` (store and
    forward to InfluxDB) or :meth:`gateway.outputs.local_store.LocalStore.write` (embedded).
    """

    def sink(record: CycleRecord) -> None:
        write(points_from_record(record, epoch_s))

    return sink
