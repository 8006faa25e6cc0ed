"""What crossed a socat pty pair, frame by frame: a wire tap for Modbus RTU tests.

``socat -x`` (``socat_pty_pair(..., hexdump=True)``) logs each chunk it passes
with its direction and a time stamp: ``<`` from the client side (ttyB) to the
server (ttyA), ``>`` back. :func:`read_wire` cuts each direction's byte stream
into RTU frames by function code and checks every CRC with pymodbus's own; bytes
that do not make a frame are counted as framing errors, and :func:`collisions`
counts requests sent while a reply to the previous one was still owed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from pymodbus.framer.rtu import FramerRTU

_HEADER = re.compile(r"^([<>]) (\d{4}/\d\d/\d\d \d\d:\d\d:\d\d)\.(\d+)\s+length=(\d+)")
#: Read requests (FC3, FC4) are 8 bytes: id, function, address, count, CRC.
_REQUEST_BYTES = 8


@dataclass(frozen=True)
class Frame:
    """One CRC-valid RTU frame: ``to_server`` is a request; ``time_s`` is socat's stamp."""

    to_server: bool
    device_id: int
    function_code: int
    time_s: float
    raw: bytes


@dataclass
class Wire:
    frames: list[Frame]
    framing_errors: int


def _chunks(log_path: Path) -> list[tuple[bool, float, bytes]]:
    """(to the server, time stamp, bytes) per chunk socat passed, in order.

    socat 1.7.4 prints the microseconds of a stamp padded to nine digits; a later
    version printing nanoseconds shows fractions of a million or more, and is read so.
    """
    chunks: list[tuple[bool, float, int, bytearray]] = []
    for line in log_path.read_text(errors="replace").splitlines():
        header = _HEADER.match(line)
        if header is not None:
            direction, stamp, fraction, _length = header.groups()
            seconds = datetime.strptime(stamp, "%Y/%m/%d %H:%M:%S").timestamp()
            chunks.append((direction == "<", seconds, int(fraction), bytearray()))
        elif chunks and line.startswith(" "):
            chunks[-1][3].extend(bytes.fromhex(line))
    scale = 1e9 if any(fraction >= 1_000_000 for _, _, fraction, _ in chunks) else 1e6
    return [(to_server, s + f / scale, bytes(data)) for to_server, s, f, data in chunks]


def _frame_size(data: bytes, to_server: bool) -> int | None:
    """Length of the frame at the start of ``data`` (None: not enough bytes to tell)."""
    if len(data) < 3:
        return None
    function_code = data[1]
    if to_server:
        return _REQUEST_BYTES
    if function_code & 0x80:
        return 5  # exception reply: id, function | 0x80, code, CRC
    return 3 + data[2] + 2  # read reply: id, function, byte count, data, CRC


def read_wire(log_path: Path) -> Wire:
    """Every frame that crossed the pair, in order, and the bytes that made none."""
    frames: list[Frame] = []
    errors = 0
    pending = {True: bytearray(), False: bytearray()}
    for to_server, time_s, data in _chunks(log_path):
        buffer = pending[to_server]
        buffer.extend(data)
        while (size := _frame_size(bytes(buffer), to_server)) is not None and len(buffer) >= size:
            body, crc = bytes(buffer[: size - 2]), int.from_bytes(buffer[size - 2 : size], "big")
            if FramerRTU.check_CRC(body, crc):
                frames.append(Frame(to_server, body[0], body[1], time_s, bytes(buffer[:size])))
                del buffer[:size]
            else:
                errors += 1
                del buffer[:1]  # hunt for the next frame start
    errors += sum(1 for buffer in pending.values() if buffer)  # a torn frame at the end
    return Wire(frames, errors)


def collisions(frames: list[Frame], silent: set[int]) -> int:
    """Requests sent while the previous request (to a device that answers) had no reply yet,
    and replies that do not come from the device just asked."""
    count = 0
    owed: int | None = None
    for frame in frames:
        if frame.to_server:
            if owed is not None:
                count += 1
            owed = None if frame.device_id in silent else frame.device_id
        else:
            if owed != frame.device_id:
                count += 1
            owed = None
    return count
