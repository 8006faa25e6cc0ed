"""One fast pass over a CSV file's bytes, before any parser sees it.

The C parser that reads the numbers says nothing useful about a broken file:
a Latin-1 byte gives ``'utf-8' codec can't decode byte 0xb0 in position 9``
(position in its own buffer, no line), a NUL byte silently cuts a cell short,
and a row with too few fields is padded with empty cells as if they had been
left blank. This pass finds each of these by line and column, reading the file
in blocks of ``BLOCK_BYTES`` so that a file of any size costs a few megabytes:

- bytes that are not UTF-8 (a UTF-8 byte order mark is accepted);
- a NUL byte (binary data);
- a row whose number of fields differs from the header's (a blank line is
  allowed: it is a row of empty cells, skipped and reported later);
- a quoted cell that runs over a line break (one row per line is expected, so
  that every message can name the line).

It returns the number of lines after the header, so the reader can size its
arrays once.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

BLOCK_BYTES = 8 << 20
NEWLINE, COMMA, QUOTE, CR = 10, 44, 34, 13


@dataclass(frozen=True)
class TextProblem:
    """Where a file stops being a CSV file of the header's shape, and why."""

    line: int
    field: int | None  # 0-based field index on that line, if known
    reason: str


def scan(path: Path, n_fields: int) -> int | TextProblem:
    """Data lines after the header, or the first problem found."""
    first_line = 1  # file line of the block's first byte
    carry = b""
    with path.open("rb") as handle:
        while True:
            block = handle.read(BLOCK_BYTES)
            data = carry + block
            if block:
                cut = data.rfind(b"\n") + 1
                data, carry = data[:cut], data[cut:]
            else:
                carry = b""
            if data:
                problem = _check_block(data, first_line, n_fields)
                if problem is not None:
                    return problem
                first_line += data.count(b"\n")
            if not block:
                break
    # ``first_line`` is now the number of the line after the last newline;
    # a last line without a newline is a line too.
    return first_line - 1 - 1 + (1 if _ends_without_newline(path) else 0)


def _ends_without_newline(path: Path) -> bool:
    with path.open("rb") as handle:
        handle.seek(0, 2)
        if handle.tell() == 0:
            return False
        handle.seek(-1, 2)
        return handle.read(1) != b"\n"


def _check_block(data: bytes, first_line: int, n_fields: int) -> TextProblem | None:
    """Problems in whole lines ``data`` (ends with a newline except at the end of the file)."""
    errors: list[tuple[int, str]] = []
    nul = data.find(b"\0")
    if nul >= 0:
        errors.append((nul, "a NUL byte: binary data where text was expected"))
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        errors.append((exc.start, undecodable(data[exc.start])))
    if errors:
        position, reason = min(errors)
        line_start = data.rfind(b"\n", 0, position) + 1
        return TextProblem(
            line=first_line + data.count(b"\n", 0, position),
            field=_field_index(data[line_start:position]),
            reason=reason,
        )
    if QUOTE in data:
        return _check_quoted(data.decode("utf-8"), first_line, n_fields)
    return _check_field_counts(data, first_line, n_fields)


def undecodable(byte: int) -> str:
    return f"not UTF-8 text: byte 0x{byte:02x} cannot be decoded (save the file as UTF-8)"


def _field_index(line_prefix: bytes) -> int | None:
    if b'"' in line_prefix:
        return None  # commas may be quoted: the field cannot be told by counting
    return line_prefix.count(b",")


def _check_field_counts(data: bytes, first_line: int, n_fields: int) -> TextProblem | None:
    """Field counts by counting commas per line (no quotes in ``data``)."""
    raw = np.frombuffer(data, dtype=np.uint8)
    ends = np.flatnonzero(raw == NEWLINE)
    if raw[-1] != NEWLINE:
        ends = np.append(ends, raw.size)
    starts = np.r_[0, ends[:-1] + 1]
    commas = np.flatnonzero(raw == COMMA)
    fields = np.searchsorted(commas, ends) - np.searchsorted(commas, starts) + 1
    length = ends - starts
    last = np.where(length > 0, raw[np.maximum(ends - 1, 0)], 0)
    blank = (length == 0) | ((length == 1) & (last == CR))
    wrong = (fields != n_fields) & ~blank
    if not wrong.any():
        return None
    row = int(np.argmax(wrong))
    return TextProblem(
        line=first_line + row,
        field=None,
        reason=f"expected {n_fields} fields as in the header, found {int(fields[row])}",
    )


def _check_quoted(text: str, first_line: int, n_fields: int) -> TextProblem | None:
    """The same checks through the csv module, which knows quoting (rare, slower)."""
    reader = csv.reader(io.StringIO(text, newline=""))
    line = first_line
    for record in reader:
        if reader.line_num - (line - first_line) > 1:
            broken = [i for i, cell in enumerate(record) if "\n" in cell or "\r" in cell]
            return TextProblem(
                line=line,
                field=broken[0] if broken else None,
                reason="a quoted cell runs over a line break; one row per line was expected",
            )
        if record and len(record) != n_fields:
            return TextProblem(
                line=line,
                field=None,
                reason=f"expected {n_fields} fields as in the header, found {len(record)}",
            )
        line = first_line + reader.line_num
    return None
