"""A point as one typed row of the local store, and back: no JSON text per point.

Every measurement shares one wide row: the tags the gateway writes (``machine``,
``sensor``, ``quality``, ``regime``, ``model_id``) and the fields it writes each
have a typed column; a column a point does not use is empty (NULL), which costs
next to nothing in a columnar file. Anything else — another tag, another field, a
known field with another type (an integer ``speed_rpm``) or a value that is not
finite — goes to the ``tags_extra`` / ``fields_extra`` JSON columns, so every
point comes back exactly as written (:func:`point_of`). An empty tag value is not
kept (InfluxDB does not keep one either).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import cast

from gateway.outputs.points import FieldValue, Point

TAGS = ("machine", "sensor", "quality", "regime", "model_id")
FLOAT_FIELDS = (
    "speed_rpm",
    "predicted_um",
    "target_um",
    "applied_um",
    "written_cnc",
    "correction_um",
    "interval_um",
    "value_C",
    "error_um",
)
INT_FIELDS = ("link_errors",)
TEXT_FIELDS = ("training_span", "outside_inputs", "write_status", "reason")
#: In the order the gateway writes them (a point read back lists them so).
FIELDS = (
    *FLOAT_FIELDS[:7],
    "training_span",
    "outside_inputs",
    "write_status",
    "link_errors",
    "value_C",
    "reason",
    "error_um",
)
#: Every column in order: measurement, the tags, the time, the fields, the JSON rest.
COLUMNS = ("measurement", *TAGS, "tags_extra", "time_ns", *FIELDS, "fields_extra")
TIME_INDEX = COLUMNS.index("time_ns")
_FIRST_FIELD = TIME_INDEX + 1
_KIND = {
    **dict.fromkeys(FLOAT_FIELDS, "float"),
    **dict.fromkeys(INT_FIELDS, "int"),
    **dict.fromkeys(TEXT_FIELDS, "text"),
}
_TAG_SET = frozenset(TAGS)

Row = tuple[object, ...]


def _fits(kind: str, value: object) -> bool:
    if kind == "float":
        return type(value) is float and math.isfinite(value)
    if kind == "int":
        return type(value) is int and -(2**63) <= value < 2**63
    return type(value) is str


def _json(data: dict) -> str | None:
    return json.dumps(data, separators=(",", ":"), ensure_ascii=False) if data else None


_SLOT = {name: i for i, name in enumerate(COLUMNS)}
_FLOAT_SLOT = {name: _SLOT[name] for name in FLOAT_FIELDS}
_EMPTY: list[object] = ["", *[""] * len(TAGS), "", 0, *[None] * len(FIELDS), None]


def row_of(point: Point) -> Row:
    """The typed row of ``point`` (in :data:`COLUMNS` order); tags are ``""`` when absent.

    Written for speed (it runs for every point the gateway logs): one list filled by
    column slot, the JSON rest only made when a point has one."""
    row = _EMPTY.copy()
    row[0] = point.measurement
    row[TIME_INDEX] = point.time_ns
    extra_tags = None
    for name, value in point.tags.items():
        if name in _TAG_SET:
            row[_SLOT[name]] = value
        elif value != "":
            extra_tags = extra_tags or {}
            extra_tags[name] = value
    if extra_tags:
        row[TIME_INDEX - 1] = _json(dict(sorted(extra_tags.items())))
    extra_fields = None
    for name, field in point.fields.items():
        slot = _FLOAT_SLOT.get(name)
        if slot is not None and type(field) is float and field - field == 0.0:  # finite
            row[slot] = field
        elif name in _KIND and slot is None and _fits(_KIND[name], field):
            row[_SLOT[name]] = field
        else:
            extra_fields = extra_fields or {}
            extra_fields[name] = field
    if extra_fields:
        row[-1] = _json(extra_fields)
    return tuple(row)


def point_of(row: Sequence[object]) -> Point:
    """The point a row (in :data:`COLUMNS` order) was made from."""
    tags = {t: str(v) for t, v in zip(TAGS, row[1:TIME_INDEX], strict=False) if v}
    if row[TIME_INDEX - 1]:
        tags.update(json.loads(str(row[TIME_INDEX - 1])))
    fields: dict[str, FieldValue] = {}
    for name, value in zip(FIELDS, row[_FIRST_FIELD:-1], strict=True):
        if value is None or (isinstance(value, float) and math.isnan(value)):
            continue
        kind = _KIND[name]
        if kind == "float":
            fields[name] = float(cast(float, value))
        elif kind == "int":
            fields[name] = int(cast(int, value))
        else:
            fields[name] = str(value)
    if row[-1]:
        fields.update(json.loads(str(row[-1])))
    return Point(str(row[0]), tags, fields, int(cast(int, row[TIME_INDEX])))
