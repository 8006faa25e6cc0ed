"""Register codecs shared by the Modbus clients (``drivers``) and the simulated devices.

Pure functions on 16-bit words, so the bit patterns on the wire (two's complement,
the Pt100 module's fault codes, float32 word order) are one definition on both ends
of a link and are unit-tested without a socket.
"""

from __future__ import annotations

import math
import struct
from typing import cast

#: Value-register fault codes of a temperature channel (signed int16 view).
OPEN_CIRCUIT_CODE = 32767  # 0x7FFF
SHORT_CIRCUIT_CODE = -32768  # 0x8000 as an unsigned register
INT16_MIN = -32768
INT16_MAX = 32767


def int16_to_register(value: int) -> int:
    """Two's-complement int16 → the unsigned 16-bit word that goes on the wire."""
    if not INT16_MIN <= value <= INT16_MAX:
        raise ValueError(f"{value} does not fit a signed 16-bit register")
    return value & 0xFFFF


def register_to_int16(register: int) -> int:
    """Unsigned 16-bit word from the wire → signed int16 (what a client decodes)."""
    if not 0 <= register <= 0xFFFF:
        raise ValueError(f"{register} is not a 16-bit register value")
    return register - 0x10000 if register & 0x8000 else register


def float32_to_registers(value: float) -> tuple[int, int]:
    """IEEE-754 float32 → two registers, high word first (big-endian word order).

    A value beyond float32 range becomes ±inf, as a C cast on the CNC would make it.
    """
    try:
        raw = struct.pack(">f", value)
    except OverflowError:
        raw = struct.pack(">f", math.copysign(math.inf, value))
    high, low = struct.unpack(">HH", raw)
    return high, low


def registers_to_float32(high: int, low: int) -> float:
    """Two registers, high word first → the float32 value (as a Python float)."""
    return cast(float, struct.unpack(">f", struct.pack(">HH", high, low))[0])


def registers_to_float32_shortest(high: int, low: int) -> float:
    """Like :func:`registers_to_float32`, but the shortest decimal with the same float32 bits.

    A client that writes 0.0125 sends 0x3C4CCCCD, which is 0.012500000186264515 when
    widened to a double. The machine should apply what the client meant, so the value
    is the shortest decimal (≤ 9 significant digits) that encodes to the same bits;
    it is still exactly what the registers hold, so a read-back is bit-identical.
    """
    value = registers_to_float32(high, low)
    if not math.isfinite(value):
        return value
    raw = struct.pack(">HH", high, low)
    for digits in range(1, 10):
        candidate = float(f"{value:.{digits}g}")
        if struct.pack(">f", candidate) == raw:
            return candidate
    return value
