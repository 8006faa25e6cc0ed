"""A register map made ready for the wire: the read requests, and each field's conversion.

:class:`DeviceRegisters` is built once per device from its
:class:`drivers.schema.RegisterMap`. The client asks it which requests to send
(one per contiguous block of one register type, split as the ``workarounds``
say) and hands it the replies to decode; the simulated device asks it for the
same blocks to serve and encodes its values with it. Both ends therefore agree
by construction, whatever the byte and word order.

Consecutive fields of one data type and order inside a request are converted
by one pymodbus call, so a module's eight channels cost one conversion, not eight.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property

from drivers.register_codec import decode_many, encode, shortest_float32
from drivers.schema import (
    FaultConvention,
    MacroBlock,
    Order,
    RegisterField,
    RegisterMap,
    Workarounds,
    integer_range,
)


@dataclass(frozen=True)
class ReadRequest:
    """One read: FC3 (``holding``) or FC4 (``input``) of ``count`` registers from ``address``."""

    register_type: str
    address: int
    count: int

    @property
    def function_code(self) -> int:
        return 3 if self.register_type == "holding" else 4


@dataclass(frozen=True)
class FieldCodec:
    """One field, resolved against its map's defaults."""

    name: str
    register_type: str
    address: int
    width: int
    data_type: str
    byte_order: Order
    word_order: Order
    scale: float
    offset: float
    status: str | None

    @property
    def end(self) -> int:
        return self.address + self.width

    @cached_property
    def divisor(self) -> float | None:
        """k when the scale is 1/k (0.1 → 10), else None."""
        inverse = 1.0 / self.scale
        return inverse if inverse == round(inverse) else None

    def value(self, raw: float) -> float:
        """Engineering value of a raw value: ``raw · scale + offset``.

        A scale of 1/k (0.1, 0.01) divides by k instead: 235 / 10 is the double
        nearest 23.5, while 3 × 0.1 is 0.30000000000000004.
        """
        divisor = self.divisor
        if divisor is not None:
            return raw / divisor + self.offset
        return raw * self.scale + self.offset

    def raw(self, value: float) -> tuple[float, bool]:
        """(raw value, clamped) for an engineering value: what a device puts in the register.

        An integer type rounds to the nearest count, ties away from zero (so +x.x5 and
        −x.x5 stay symmetric), and clamps to its range (``clamped`` True; NaN clamps high).
        """
        divisor = self.divisor
        counts = (value - self.offset) * divisor if divisor else (value - self.offset) / self.scale
        bounds = integer_range(self.data_type)
        if bounds is None:
            return counts, False
        low, high = bounds
        if math.isnan(counts) or counts > high:
            return high, True
        if counts < low:
            return low, True
        return int(math.copysign(math.floor(abs(counts) + 0.5), counts)), False


class _Run:
    """Consecutive same-typed fields inside one request: decoded by one pymodbus call.

    The last registers and their values are kept: a temperature changes its
    0.1 °C counts every few seconds, so most cycles convert nothing.
    """

    def __init__(self, offset: int, fields: tuple[FieldCodec, ...]) -> None:
        self.offset = offset  # first register, counted in the concatenated replies
        self.fields = fields
        self._end = offset + fields[0].width * len(fields)
        self._last: tuple[list[int], list[float]] | None = None

    def decode(self, registers: Sequence[int], into: dict[str, float]) -> None:
        words = list(registers[self.offset : self._end])
        last = self._last
        if last is not None and last[0] == words:
            values = last[1]
        else:
            first = self.fields[0]
            if first.width == 1:
                values = _single_registers(words, first.data_type, first.byte_order)
            else:
                values = decode_many(words, first.data_type, first.byte_order, first.word_order)
                if first.data_type == "float32":
                    values = [shortest_float32(v) for v in values]
            self._last = (words, values)
        for codec, raw in zip(self.fields, values, strict=True):
            into[codec.name] = raw


#: Values of single 16-bit registers already converted, by (data type, byte order).
#: At most 65 536 entries each: a register has no more values.
_WORDS: dict[tuple[str, str], dict[int, float]] = {}


def _single_registers(words: list[int], data_type: str, byte_order: Order) -> list[float]:
    """int16/uint16 values of registers; pymodbus converts only words not seen before."""
    known = _WORDS.setdefault((data_type, byte_order), {})
    missing = [w for w in words if w not in known]
    if missing:
        for word, value in zip(missing, decode_many(missing, data_type, byte_order), strict=True):
            known[word] = value
    return [known[w] for w in words]


class MacroLayout:
    """A CNC's macro variables in its registers: where #n is, and its value's encoding."""

    def __init__(self, block: MacroBlock, register_map: RegisterMap) -> None:
        self.first = block.first
        self.last = block.last
        self.address = block.address
        self.end = block.end
        self.width = block.width
        self.data_type = block.data_type
        self.byte_order: Order = block.byte_order or register_map.byte_order
        self.word_order: Order = block.word_order or register_map.word_order

    def register(self, number: int) -> int:
        """First register of macro #number."""
        if not self.first <= number <= self.last:
            raise ValueError(f"macro #{number} is outside the mapped #{self.first}–#{self.last}")
        return self.address + self.width * (number - self.first)

    def number(self, register: int) -> int:
        """The macro whose value starts at ``register`` (aligned, inside the block)."""
        return self.first + (register - self.address) // self.width

    def encode(self, value: float) -> list[int]:
        if not self.data_type.startswith("float"):
            value = int(value)
        return encode(value, self.data_type, self.byte_order, self.word_order)

    def decode(self, registers: Sequence[int]) -> float:
        """A macro's value from its registers (a float32 as its shortest decimal)."""
        value = decode_many(registers, self.data_type, self.byte_order, self.word_order)[0]
        return shortest_float32(value) if self.data_type == "float32" else float(value)


class DeviceRegisters:
    """What a device's register map means on the wire, for a client and a server alike."""

    def __init__(self, register_map: RegisterMap, workarounds: Workarounds | None = None) -> None:
        self.map = register_map
        self.workarounds = workarounds if workarounds is not None else register_map.workarounds
        self.fields = {item.name: self._resolve(item) for item in register_map.fields}
        self.faults: FaultConvention | None = register_map.faults
        faults = register_map.faults
        #: The fault convention as look-ups: the good status, texts by status, names by code.
        self.ok_status = faults.status_codes["ok"] if faults is not None else 0
        self.status_texts = (
            {c: fault_meaning(n) for n, c in faults.status_codes.items() if n != "ok"}
            if faults is not None
            else {}
        )
        self.value_code_names = (
            {c: n for n, c in faults.value_codes.items()} if faults is not None else {}
        )
        self.channels = tuple(self.fields[name] for name in register_map.channels)
        self.requests = self._plan()
        self._runs = self._runs_of(self.requests)
        self.macros = (
            MacroLayout(register_map.macros, register_map) if register_map.macros else None
        )

    def _resolve(self, item: RegisterField) -> FieldCodec:
        m = self.map
        return FieldCodec(
            name=item.name,
            register_type=m.kind_of(item),
            address=item.address,
            width=item.width,
            data_type=item.data_type,
            byte_order=item.byte_order or m.byte_order,
            word_order=item.word_order or m.word_order,
            scale=item.scale,
            offset=item.offset,
            status=item.status,
        )

    # -- blocks and requests ---------------------------------------------------------

    def blocks(self) -> list[tuple[str, int, list[FieldCodec]]]:
        """Contiguous runs of fields, per register type: (type, first address, fields)."""
        ordered = sorted(self.fields.values(), key=lambda f: (f.register_type, f.address))
        blocks: list[tuple[str, int, list[FieldCodec]]] = []
        for codec in ordered:
            if blocks:
                kind, _, members = blocks[-1]
                if kind == codec.register_type and members[-1].end == codec.address:
                    members.append(codec)
                    continue
            blocks.append((codec.register_type, codec.address, [codec]))
        return blocks

    def _plan(self) -> tuple[ReadRequest, ...]:
        """One request per contiguous block, split at the limit, or one per field."""
        limit = self.workarounds.max_registers_per_request
        requests: list[ReadRequest] = []
        for kind, _, members in self.blocks():
            if self.workarounds.one_request_per_field:
                requests += [ReadRequest(kind, f.address, f.width) for f in members]
                continue
            start, count = members[0].address, 0
            for codec in members:  # a field never straddles two requests
                if count + codec.width > limit:
                    requests.append(ReadRequest(kind, start, count))
                    start, count = codec.address, 0
                count += codec.width
            requests.append(ReadRequest(kind, start, count))
        return tuple(requests)

    def _runs_of(self, requests: Sequence[ReadRequest]) -> tuple[_Run, ...]:
        runs: list[_Run] = []
        offset = 0
        for request in requests:
            members = [
                f
                for f in self.fields.values()
                if f.register_type == request.register_type
                and request.address <= f.address < request.address + request.count
            ]
            members.sort(key=lambda f: f.address)
            current: list[FieldCodec] = []
            for codec in members:
                if current and _same_conversion(current[-1], codec):
                    current.append(codec)
                    continue
                if current:
                    runs.append(_Run(offset + current[0].address - request.address, tuple(current)))
                current = [codec]
            if current:
                runs.append(_Run(offset + current[0].address - request.address, tuple(current)))
            offset += request.count
        return tuple(runs)

    @property
    def register_count(self) -> int:
        """Registers read per cycle (the sum over the requests)."""
        return sum(request.count for request in self.requests)

    # -- client side -------------------------------------------------------------------

    def decode_raw(self, registers: Sequence[int]) -> dict[str, float]:
        """Raw value of every field from the replies to :attr:`requests`, concatenated in order."""
        if len(registers) != self.register_count:
            raise ValueError(
                f"register map {self.map.label}: {len(registers)} registers, "
                f"{self.register_count} expected"
            )
        raws: dict[str, float] = {}
        for run in self._runs:
            run.decode(registers, raws)
        return raws

    def decode(self, registers: Sequence[int]) -> dict[str, float]:
        """Engineering value (scale and offset applied) of every field."""
        raws = self.decode_raw(registers)
        return {name: self.fields[name].value(raw) for name, raw in raws.items()}

    # -- server side -------------------------------------------------------------------

    def encode_block(self, members: Sequence[FieldCodec], raws: Mapping[str, float]) -> list[int]:
        """The registers of one block (from :meth:`blocks`) for raw values (missing: 0)."""
        registers: list[int] = []
        for codec in members:
            raw = raws.get(codec.name, 0)
            if codec.data_type.startswith("float"):
                value: float = float(raw)
            else:
                value = int(raw)
            registers += encode(value, codec.data_type, codec.byte_order, codec.word_order)
        return registers


def _same_conversion(a: FieldCodec, b: FieldCodec) -> bool:
    return (
        a.end == b.address
        and a.data_type == b.data_type
        and a.byte_order == b.byte_order
        and a.word_order == b.word_order
    )


def fault_meaning(code_name: str) -> str:
    """``open_circuit`` → ``open circuit``: a convention's key as the text a reading carries."""
    return code_name.replace("_", " ")
