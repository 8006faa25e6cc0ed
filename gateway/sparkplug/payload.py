"""Sparkplug B payloads from and to the spec's protobuf messages (``sparkplug_b_pb2``).

A metric is described once (:class:`MetricSpec`: name, datatype, unit, alias); births
carry name, alias, datatype and the unit as the ``engUnit`` property, data messages
only the alias (a metric without an alias, ``Node Control/Rebirth``, goes by its name
everywhere). Values are set in the protobuf field the datatype calls for.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from gateway.sparkplug import sparkplug_b_pb2 as pb

Payload = pb.Payload

INT64 = pb.Int64
UINT64 = pb.UInt64
DOUBLE = pb.Double
BOOLEAN = pb.Boolean
STRING = pb.String

DATATYPE_NAMES: dict[int, str] = {
    INT64: "Int64",
    UINT64: "UInt64",
    DOUBLE: "Double",
    BOOLEAN: "Boolean",
    STRING: "String",
}
_VALUE_FIELD: dict[int, str] = {
    INT64: "long_value",
    UINT64: "long_value",
    DOUBLE: "double_value",
    BOOLEAN: "boolean_value",
    STRING: "string_value",
}

Value = float | int | bool | str | None


@dataclass(frozen=True)
class MetricSpec:
    """One metric: its name, Sparkplug datatype, alias (None: by name only) and
    engineering unit (or "")."""

    name: str
    datatype: int
    alias: int | None
    unit: str = ""


def _set_value(metric: pb.Payload.Metric, datatype: int, value: Value) -> None:
    if value is None or (datatype == DOUBLE and value != value):  # NaN travels as null
        metric.is_null = True
        return
    field = _VALUE_FIELD[datatype]
    if datatype == INT64:
        value = int(value) & 0xFFFF_FFFF_FFFF_FFFF  # the spec's two's complement in a uint64
    elif datatype == UINT64:
        value = max(int(value), 0)
    elif datatype == DOUBLE:
        value = float(value)
    elif datatype == BOOLEAN:
        value = bool(value)
    else:
        value = str(value)
    setattr(metric, field, value)


def value_of(metric: pb.Payload.Metric) -> Value:
    """The value a received metric carries (None when null or absent)."""
    if metric.is_null:
        return None
    kind = metric.WhichOneof("value")
    return None if kind is None else getattr(metric, kind)


def encode(
    specs: Iterable[MetricSpec],
    values: Mapping[str, Value],
    *,
    seq: int | None,
    timestamp_ms: int,
    birth: bool = False,
    historical: bool = False,
) -> bytes:
    """A payload with one metric per spec (its value from ``values``)."""
    payload = pb.Payload(timestamp=timestamp_ms)
    if seq is not None:
        payload.seq = seq
    for spec in specs:
        metric = payload.metrics.add(timestamp=timestamp_ms)
        metric.datatype = spec.datatype
        if spec.alias is not None:
            metric.alias = spec.alias
        if birth or spec.alias is None:
            metric.name = spec.name
            if spec.unit:
                metric.properties.keys.append("engUnit")
                metric.properties.values.add(type=STRING, string_value=spec.unit)
        if historical:
            metric.is_historical = True
        _set_value(metric, spec.datatype, values.get(spec.name))
    return payload.SerializeToString()


def decode(data: bytes) -> pb.Payload:
    """A received payload; ValueError when the bytes are not one."""
    payload = pb.Payload()
    try:
        payload.ParseFromString(data)
    except Exception as exc:  # protobuf's DecodeError and friends
        raise ValueError(f"not a Sparkplug B payload: {exc}") from None
    return payload
