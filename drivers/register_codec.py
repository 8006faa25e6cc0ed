"""Register conversion shared by the Modbus clients (``drivers``) and the simulated devices.

The conversion itself is pymodbus's (``ModbusClientMixin.convert_to_registers`` and
``convert_from_registers``, with their ``word_order``); this module adds what
pymodbus leaves out: the byte order within a register (pymodbus is big-endian
only), float32 overflow as ±inf (as a C cast on a CNC makes it), and the shortest
decimal for a float32. Pure functions on 16-bit words, so both ends of a link
share one definition and it is unit-tested without a socket.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any, cast

from pymodbus.client.mixin import ModbusClientMixin

from drivers.schema import Order

#: Value-register fault codes of the Pt100 module's channels (signed int16 view).
OPEN_CIRCUIT_CODE = 32767  # 0x7FFF
SHORT_CIRCUIT_CODE = -32768  # 0x8000 as an unsigned register
INT16_MIN = -32768
INT16_MAX = 32767

DATATYPES: dict[str, Any] = {
    name: ModbusClientMixin.DATATYPE[name.upper()]
    for name in ("int16", "uint16", "int32", "uint32", "float32", "int64", "uint64", "float64")
}


def swap_bytes(registers: Sequence[int]) -> list[int]:
    """Each 16-bit register with its two bytes exchanged (little-endian byte order)."""
    return [((r & 0xFF) << 8) | (r >> 8) for r in registers]


def encode(
    value: float, data_type: str, byte_order: Order = "big", word_order: Order = "big"
) -> list[int]:
    """One value → its registers in the given byte and word order.

    An integer type takes an int (``ValueError`` if it does not fit); a float32
    beyond float32's range becomes ±inf.
    """
    kind = DATATYPES[data_type]
    if data_type == "float32" and math.isfinite(value) and abs(value) > _FLOAT32_MAX:
        value = math.copysign(math.inf, value)
    try:
        registers = ModbusClientMixin.convert_to_registers(value, kind, word_order=word_order)
    except struct.error:
        raise ValueError(f"{value!r} does not fit {data_type}") from None
    return swap_bytes(registers) if byte_order == "little" else registers


def decode_many(
    registers: Sequence[int], data_type: str, byte_order: Order = "big", word_order: Order = "big"
) -> list[float]:
    """Consecutive values of one data type from their registers (one pymodbus call)."""
    words = swap_bytes(registers) if byte_order == "little" else list(registers)
    values = ModbusClientMixin.convert_from_registers(
        words, DATATYPES[data_type], word_order=word_order
    )
    return cast(list[float], values) if isinstance(values, list) else [cast(float, values)]


def decode(
    registers: Sequence[int], data_type: str, byte_order: Order = "big", word_order: Order = "big"
) -> float:
    """One value from its registers."""
    return decode_many(registers, data_type, byte_order, word_order)[0]


_FLOAT32_MAX = 3.4028234663852886e38


def shortest_float32(value: float) -> float:
    """The shortest decimal (≤ 9 significant digits) with the same float32 bits as ``value``.

    A client that writes 0.0125 sends 0x3C4CCCCD, which is 0.012500000186264515 when
    widened to a double. The machine should apply what the client meant, so the value
    is the shortest decimal that encodes to the same bits; it is still exactly what
    the registers hold, so a read-back is bit-identical.
    """
    if not math.isfinite(value):
        return value
    raw = struct.pack(">f", value)
    for digits in range(1, 10):
        candidate = float(f"{value:.{digits}g}")
        if struct.pack(">f", candidate) == raw:
            return candidate
    return value


def int16_to_register(value: int) -> int:
    """Two's-complement int16 → the unsigned 16-bit word that goes on the wire."""
    if not INT16_MIN <= value <= INT16_MAX:
        raise ValueError(f"{value} does not fit a signed 16-bit register")
    return encode(value, "int16")[0]


def register_to_int16(register: int) -> int:
    """Unsigned 16-bit word from the wire → signed int16 (what a client decodes)."""
    if not 0 <= register <= 0xFFFF:
        raise ValueError(f"{register} is not a 16-bit register value")
    return int(decode([register], "int16"))


def float32_to_registers(value: float) -> tuple[int, int]:
    """IEEE-754 float32 → two registers, high word first (big-endian word order)."""
    high, low = encode(value, "float32")
    return high, low


def registers_to_float32(high: int, low: int) -> float:
    """Two registers, high word first → the float32 value (as a Python float)."""
    return decode([high, low], "float32")


def registers_to_float32_shortest(high: int, low: int) -> float:
    """Like :func:`registers_to_float32`, but the shortest decimal with the same bits."""
    return shortest_float32(registers_to_float32(high, low))
