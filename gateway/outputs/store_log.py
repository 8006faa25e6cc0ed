"""The local store's open period: append-only segment files, one compact record per commit.

Each commit (once a second in the gateway) appends one record to the segment of the
10-minute period its points belong to and flushes it to the disk, so a second costs
about what it stores: no page of the file is ever written twice. A record is

    b"GWL1" | payload length (u32 LE) | CRC-32 of the payload (u32 LE) | payload

and the payload is a zlib (deflate) stream of the second's rows as columns: the
measurement and tag columns (skipped when they equal the record before's, as they
do second after second for a steady fleet), the text field columns as JSON, and
each number column as the smallest of: nothing (all empty), a reference to an equal
column, integers of the value × 10^k (exact for values read to k decimals), as
differences to the record before's when its series are the same, or raw float64.
A SIGKILL or power cut mid-append leaves a record cut short or with a wrong CRC at
the end of a segment: readers stop before it and the writer cuts it off when it
opens the segment again, so a crash loses at most the commit under way.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gateway.outputs.points import Point
from gateway.outputs.store_rows import (
    COLUMNS,
    FLOAT_FIELDS,
    INT_FIELDS,
    TAGS,
    TEXT_FIELDS,
    TIME_INDEX,
    row_of,
)

MAGIC = b"GWL1"
HEADER = struct.Struct("<4sII")
_BODY = struct.Struct("<IIB")  # rows, JSON length, flags
SAME_KEYS = 1  # the record's key columns are the record before's
DUPLICATES = 2  # a row repeats a key written before in the segment (fields merged on read)
LEVEL = 6  # zlib level: 6 writes 20 % less than 1 for a few µs a machine-second more
SCALES = range(7)  # decimals tried for a number column stored as integers

KEY_COLUMNS = COLUMNS[:TIME_INDEX]  # measurement, the tags, tags_extra
SORT_KEYS = ("measurement", *TAGS, "tags_extra")  # a part's order (then time)
_NUMBERS = frozenset((*FLOAT_FIELDS, *INT_FIELDS, "time_ns"))
NUMBER_COLUMNS = tuple(c for c in COLUMNS if c in _NUMBERS)
TEXT_COLUMNS = tuple(c for c in COLUMNS[TIME_INDEX:] if c not in _NUMBERS)
_NULL = np.iinfo(np.int64).min  # an empty number among integers


@dataclass
class Chain:
    """What the next record may refer to: the record before's keys and integer columns."""

    keys: list | None = None
    ints: dict[str, tuple[int, np.ndarray]] = field(default_factory=dict)
    text: dict = field(default_factory=dict)  # the text field columns by name


def _as_ints(values: np.ndarray) -> tuple[int, np.ndarray] | None:
    """``values`` as integers × 10^-k for the smallest k that gives them back exactly."""
    finite = ~np.isnan(values)
    if not np.isfinite(values[finite]).all() or np.abs(values[finite]).max(initial=0) > 1e15:
        return None
    for k in SCALES:
        scaled = np.round(values[finite] * 10.0**k)
        if (scaled / 10.0**k == values[finite]).all():
            ints = np.full(len(values), _NULL, dtype=np.int64)
            ints[finite] = scaled.astype(np.int64)
            return k, ints
    return None


def _narrow(ints: np.ndarray) -> tuple[str, bytes]:
    """Integers in the smallest dtype that holds them (its name and the bytes)."""
    if len(ints) == 0:
        return "i1", b""
    lo, hi = int(ints.min()), int(ints.max())
    for dtype in ("i1", "i2", "i4"):
        info = np.iinfo(dtype)
        if info.min <= lo and hi <= info.max:
            return dtype, ints.astype(dtype).tobytes()
    return "i8", ints.tobytes()


def _number_column(
    name: str, values: np.ndarray, earlier: dict[str, np.ndarray], chain: Chain | None
) -> tuple[list, bytes, tuple[int, np.ndarray] | None]:
    """How one number column is stored: its descriptor, bytes and integers (if any)."""
    if name != "time_ns" and np.isnan(values).all():
        return ["n"], b"", None
    for other, seen in earlier.items():
        if np.array_equal(seen, values, equal_nan=True):
            return ["=", other], b"", None
    as_ints = (0, values) if name == "time_ns" else _as_ints(values)
    if as_ints is None:
        return ["f"], values.astype("<f8").tobytes(), None
    k, ints = as_ints
    before = chain.ints.get(name) if chain is not None else None
    if before is not None and before[0] == k and len(before[1]) == len(ints):
        null = ints == _NULL
        if (null == (before[1] == _NULL)).all():
            dtype, data = _narrow(np.where(null, 0, ints - before[1]))
            return ["d", k, dtype], data, (k, ints)
    dtype, data = _narrow(ints)
    return ["s", k, dtype], data, (k, ints)


Columns = dict[str, list]
_TAG_SET = frozenset(TAGS)
_FLOAT_SET = frozenset(FLOAT_FIELDS)
_INT_SET = frozenset(INT_FIELDS)
_TEXT_SET = frozenset(TEXT_FIELDS)


def columns_of(points: Sequence[Point]) -> Columns:
    """The typed columns of ``points``, each row as :func:`row_of` makes it.

    Written for speed (it runs for every point the gateway logs): points of one shape
    (measurement, tag and field names) are gathered as value tuples and turned into
    columns with ``zip``, so a point costs a tuple, not a Python step per value; a
    shape with a value outside its typed column takes :func:`row_of` point by point."""
    groups: dict[tuple, tuple[list, list]] = {}
    for p in points:
        shape = (p.measurement, tuple(p.tags), tuple(p.fields))
        group = groups.get(shape)
        if group is None:
            group = groups[shape] = ([], [])
        group[0].append((p.time_ns, *p.tags.values(), *p.fields.values()))
        group[1].append(p)
    out: Columns = {c: [] for c in COLUMNS}
    for shape, (rows, group_points) in groups.items():
        if not _extend_typed(out, shape, rows):
            for row in map(row_of, group_points):
                for column, value in zip(out.values(), row, strict=True):
                    column.append(value)
    return out


def _typed_column(name: str, values: tuple) -> bool:
    """Whether every value of field ``name`` fits its typed column."""
    kinds = set(map(type, values))
    if name in _FLOAT_SET:
        return kinds == {float} and bool(np.isfinite(np.array(values, dtype=float)).all())
    if name in _INT_SET:
        return kinds == {int} and all(-(2**63) <= v < 2**63 for v in values)
    return name in _TEXT_SET and kinds == {str}


def _extend_typed(out: Columns, shape: tuple, rows: list[tuple]) -> bool:
    """Append the rows of one shape to ``out`` column by column; False (nothing
    appended) when a tag or field of it is outside the typed columns."""
    measurement, tag_names, field_names = shape
    if not _TAG_SET.issuperset(tag_names):
        return False
    columns = list(zip(*rows, strict=True))
    named = dict(zip((*tag_names, *field_names), columns[1:], strict=True))
    if not all(_typed_column(f, named[f]) for f in field_names):
        return False
    n = len(rows)
    out["measurement"].extend([measurement] * n)
    for tag in TAGS:
        out[tag].extend(named.get(tag, ("",) * n))
    out["tags_extra"].extend([""] * n)
    out["time_ns"].extend(columns[0])
    for name in COLUMNS[TIME_INDEX + 1 : -1]:
        out[name].extend(named.get(name, (None,) * n))
    out["fields_extra"].extend([None] * n)
    return True


def encode(columns: Columns, chain: Chain, duplicates: bool) -> bytes:
    """One record of ``columns`` (one period's points of a commit); ``chain`` is updated."""
    keys = [columns[c] for c in KEY_COLUMNS]
    n = len(columns["time_ns"])
    same = chain.keys is not None and keys == chain.keys
    text = {c: columns[c] for c in TEXT_COLUMNS}
    doc: dict[str, object] = {  # columns by name: a column added later reads as empty
        "text": {c: 0 if same and v == chain.text.get(c) else v for c, v in text.items()}
    }  # 0: the record before's column
    if not same:
        doc["keys"] = dict(zip(KEY_COLUMNS, keys, strict=True))
    numbers: dict[str, list] = {}
    blobs: list[bytes] = []
    earlier: dict[str, np.ndarray] = {}
    ints: dict[str, tuple[int, np.ndarray]] = {}
    for name in NUMBER_COLUMNS:
        dtype = np.int64 if name == "time_ns" else float
        values = np.array(columns[name], dtype=dtype)
        described, data, as_ints = _number_column(name, values, earlier, chain if same else None)
        numbers[name] = [*described, len(data)]
        blobs.append(data)
        if name != "time_ns":
            earlier[name] = values
        if as_ints is not None:
            ints[name] = as_ints
    doc["numbers"] = numbers
    head = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode()
    flags = (SAME_KEYS if same else 0) | (DUPLICATES if duplicates else 0)
    payload = zlib.compress(_BODY.pack(n, len(head), flags) + head + b"".join(blobs), LEVEL)
    chain.keys, chain.ints, chain.text = keys, ints, text
    return HEADER.pack(MAGIC, len(payload), zlib.crc32(payload)) + payload


def _decode_numbers(
    described: list, blob: bytes, n: int, name: str, done: dict, chain: Chain
) -> tuple[np.ndarray, tuple[int, np.ndarray] | None]:
    kind = described[0]
    if kind == "n":
        return np.full(n, np.nan), None
    if kind == "=":
        return done[described[1]], None
    if kind == "f":
        return np.frombuffer(blob, dtype="<f8").copy(), None
    k, dtype = described[1], described[2]
    ints = np.frombuffer(blob, dtype=dtype).astype(np.int64)
    if kind == "d":
        null = chain.ints[name][1] == _NULL
        ints = np.where(null, _NULL, chain.ints[name][1] + ints)
    if name == "time_ns":
        return ints, (k, ints)
    values = np.where(ints == _NULL, np.nan, ints.astype(float) / 10.0**k)
    return values, (k, ints)


def decode(payload: bytes, chain: Chain) -> tuple[dict[str, np.ndarray], bool]:
    """The columns of one record's payload and whether it flagged duplicate keys."""
    body = zlib.decompress(payload)
    n, size, flags = _BODY.unpack_from(body)
    start = _BODY.size
    doc = json.loads(body[start : start + size])
    offset = start + size
    if flags & SAME_KEYS:
        key_columns = chain.keys
    else:
        key_columns = [_texts(doc["keys"].get(c), n, "") for c in KEY_COLUMNS]
    assert key_columns is not None, "a record refers to keys before the segment's first"
    columns: dict[str, np.ndarray] = dict(zip(KEY_COLUMNS, key_columns, strict=True))
    ints: dict[str, tuple[int, np.ndarray]] = {}
    for name, described in doc["numbers"].items():
        blob = body[offset : offset + described[-1]]
        offset += described[-1]
        columns[name], as_ints = _decode_numbers(described[:-1], blob, n, name, columns, chain)
        if as_ints is not None:
            ints[name] = as_ints
    for name in NUMBER_COLUMNS:  # a column the record does not name: empty
        columns.setdefault(name, np.full(n, np.nan))
    text = {}
    for name in TEXT_COLUMNS:
        values = doc["text"].get(name)
        text[name] = columns[name] = chain.text[name] if values == 0 else _texts(values, n, None)
    chain.keys, chain.ints, chain.text = key_columns, ints, text
    return {c: columns[c] for c in COLUMNS}, bool(flags & DUPLICATES)


def _texts(values: list | None, n: int, empty: str | None) -> np.ndarray:
    """A text column of a record (``empty`` in every row when the record lacks it)."""
    column = np.empty(n, dtype=object)
    column[:] = [empty] * n if values is None else values
    return column


def records(path: Path) -> Iterator[tuple[int, bytes]]:
    """Each whole record's payload in segment ``path`` with the offset after it; stops
    at the first record cut short or damaged (a crash's last append)."""
    with path.open("rb") as stream:
        data = stream.read()
    offset = 0
    while offset + HEADER.size <= len(data):
        magic, size, crc = HEADER.unpack_from(data, offset)
        payload = data[offset + HEADER.size : offset + HEADER.size + size]
        if magic != MAGIC or len(payload) != size or zlib.crc32(payload) != crc:
            return
        offset += HEADER.size + size
        yield offset, payload


def read_segment(path: Path) -> tuple[list[dict[str, np.ndarray]], bool, int, Chain]:
    """A segment's records as columns, whether any flagged duplicates, the length of
    its whole records (where a writer appends next) and the chain after the last."""
    chain = Chain()
    found, duplicates, end = [], False, 0
    for offset, payload in records(path):
        end = offset
        columns, flagged = decode(payload, chain)
        found.append(columns)
        duplicates |= flagged
    if chain.keys is not None:  # as lists, as encode compares them
        chain.keys = [list(c) for c in chain.keys]
        chain.text = {c: list(v) for c, v in chain.text.items()}
    return found, duplicates, end, chain


def concatenate(batches: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Columns of several records as one set of columns."""
    if not batches:
        return {c: _empty(c) for c in COLUMNS}
    return {c: np.concatenate([b[c] for b in batches]) for c in COLUMNS}


def ordered_columns(batches: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray] | None:
    """The ``batches`` as one set of columns sorted as a part is (by series, then time),
    when every batch holds the same series in the same rows — as a steady fleet's
    seconds do — so no sort of the whole period is needed (each row's place is known
    from its batch and its row); else None. A column is written once, in place."""
    if not batches:
        return None
    first, count = batches[0], len(batches)
    n = len(first["time_ns"])
    for batch in batches[1:]:
        if len(batch["time_ns"]) != n or any(batch[c] is not first[c] for c in KEY_COLUMNS):
            return None
    keys = list(zip(*(first[c] for c in SORT_KEYS), first["time_ns"].tolist(), strict=True))
    within = np.array(sorted(range(n), key=keys.__getitem__), dtype=np.int64)
    out: dict[str, np.ndarray] = {}
    for name in COLUMNS:
        if all(batch[name] is first[name] for batch in batches):
            out[name] = np.repeat(first[name][within], count)
            continue
        column = np.empty(n * count, dtype=first[name].dtype)
        grid = column.reshape(n, count)
        for r, batch in enumerate(batches):
            grid[:, r] = batch[name][within]
        out[name] = column
    return out


def _empty(column: str) -> np.ndarray:
    if column == "time_ns":
        return np.array([], dtype=np.int64)
    if column in _NUMBERS:
        return np.array([], dtype=float)
    return np.array([], dtype=object)


@dataclass
class SeriesTimes:
    """Each series' latest time written to a segment: whether new rows may repeat an
    identity written before (their segment's rows are then merged on read).

    Kept per series (2 200 entries for 200 machines), and for a steady fleet — the
    same series in the same rows as the record before, each later — checked with one
    array comparison, not a step per row; the record before's times are folded into
    the table only when the series change."""

    latest: dict[tuple, int] = field(default_factory=dict)
    keys: list | None = None  # the record before's key columns (each series once)
    times: np.ndarray | None = None  # and its times

    def after(self, keys: list, times: Sequence[int] | np.ndarray) -> tuple[bool, SeriesTimes]:
        """Whether every row is later than its series' latest time, and the state after
        the rows (``self`` is left as it was: the append may still fail)."""
        stamps = np.asarray(times, dtype=np.int64)
        if (
            self.keys is not None
            and self.times is not None
            and len(stamps) == len(self.times)
            and keys == self.keys
            and bool((stamps > self.times).all())
        ):
            return True, SeriesTimes(self.latest, keys, stamps)
        latest = dict(self.latest)
        if self.keys is not None and self.times is not None:
            _later_only(latest, self.keys, self.times)
        later = _later_only(latest, keys, stamps)
        once = len(set(zip(*keys, strict=True))) == len(stamps)
        return later, SeriesTimes(latest, keys if once else None, stamps if once else None)


class Segment:
    """One open segment file, appended by the writer (its whole records kept, a torn
    tail cut off when opened)."""

    def __init__(self, path: Path, sync: bool) -> None:
        self.path = path
        self.sync = sync
        self.chain = Chain()
        self.times = SeriesTimes()
        if path.exists():
            batches, _, end, self.chain = read_segment(path)
            for columns in batches:
                keys = [columns[c].tolist() for c in KEY_COLUMNS]
                _, self.times = self.times.after(keys, columns["time_ns"])
            with path.open("rb+") as stream:
                stream.truncate(end)
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self.size = os.fstat(self.fd).st_size

    def append(self, columns: Columns) -> None:
        """Append ``columns`` as one record, flushed to the disk (``sync``); on failure (a
        full disk) the segment is cut back to its whole records and the error raised."""
        later, times = self.times.after([columns[c] for c in KEY_COLUMNS], columns["time_ns"])
        duplicates = not later
        chain = Chain(self.chain.keys, self.chain.ints, self.chain.text)
        record = encode(columns, chain, duplicates)
        try:
            written = os.write(self.fd, record)
            if written != len(record):
                raise OSError(28, "No space left on device (short write)")
            if self.sync:
                os.fsync(self.fd)
        except OSError:
            os.ftruncate(self.fd, self.size)
            raise
        self.size += len(record)
        self.chain = chain
        self.times = times

    def close(self) -> None:
        os.close(self.fd)


def _later_only(latest: dict[tuple, int], keys: list, times: Sequence[int] | np.ndarray) -> bool:
    """Whether every row is later than its series' latest time in ``latest`` (then no
    row can repeat an identity written before); ``latest`` updated. A row at or before
    it (a repeat, or a clock stepped back) makes the segment's rows merged on read.
    Kept per series, not per row: a period of 200 machines holds 2 200 entries."""
    later = True
    for series, time_ns in zip(zip(*keys, strict=True), times, strict=True):
        before = latest.get(series)
        if before is not None and time_ns <= before:
            later = False
        else:
            latest[series] = int(time_ns)
    return later


def merge_duplicates(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows of one identity (measurement, tags, time) made one, in write order: a field
    written again takes the new value, the others are kept (InfluxDB's rule)."""
    from gateway.outputs.store_parts import arrays_of  # the parts' own column form

    merged: dict[tuple, list] = {}
    fields = range(TIME_INDEX + 1, len(COLUMNS) - 1)
    for row in zip(*(columns[c] for c in COLUMNS), strict=True):
        row = tuple(plain(v) for v in row)
        key = row[: TIME_INDEX + 1]
        kept = merged.get(key)
        if kept is None:
            merged[key] = list(row)
            continue
        for i in fields:
            if row[i] is not None:
                kept[i] = row[i]
        if row[-1] is not None:
            extra = json.loads(kept[-1]) if kept[-1] is not None else {}
            extra.update(json.loads(row[-1]))
            kept[-1] = json.dumps(extra, separators=(",", ":"), ensure_ascii=False)
    return arrays_of([tuple(r) for r in merged.values()])


def plain(value: object) -> object:
    """A column value as a row holds it: NaN is empty, numpy numbers Python numbers."""
    if isinstance(value, float | np.floating):
        return None if np.isnan(value) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value
