"""Shared pieces of the simulator's Modbus slaves: temperature encoding and pymodbus plumbing.

A device's registers are its register map (``drivers/maps/``), made ready for the
wire by ``drivers.register_map`` — the same code the gateway's clients decode
with, so both ends agree by construction in any byte or word order. The channel
encoder here is a pure function so that the exact bit patterns a real device would
put on the wire (fault codes, clamping) are unit-tested without a socket.
The plumbing wraps pymodbus 3.16's ``SimDevice`` model, whose only hook into a
request is the device ``action`` coroutine; both servers build on it the same way.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Collection, Coroutine
from dataclasses import dataclass
from functools import cache
from typing import Self, cast

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData

from drivers.register_map import DeviceRegisters, FieldCodec
from drivers.schema import TRANSMITTER_MAP, load_register_map
from simulator.link import ChannelReading, ChannelStatus

#: Requests an endpoint remembers in ``received``.
RECEIVED_KEPT = 1000
#: Function codes a Modbus client uses to write holding registers.
WRITE_FUNCTION_CODES = frozenset({6, 16, 22, 23})
#: Function codes that address bits (coils, discrete inputs): none of our devices has any.
BIT_FUNCTION_CODES = frozenset({1, 2, 5, 15})

#: Signature of a pymodbus ``SimDevice`` action (see pymodbus.simulator.SimAction).
Action = Callable[
    [int, int, int, int, list[int], list[int] | list[bool] | None],
    Coroutine[None, None, ExcCodes | None],
]


def encode_channel(
    layout: DeviceRegisters, channel: FieldCodec, reading: ChannelReading | None
) -> tuple[float, int | None]:
    """One transmitter channel → (raw value, raw status) under the map's fault convention.

    Counts are rounded to the nearest count, ties away from zero so that +x.x5 °C
    and −x.x5 °C stay symmetric. ``None`` is a channel without a probe attached: a
    real module sees an open input, so it reports the open-circuit code and
    status. A value that does not fit the data type (or is not a number) is
    clamped and flagged out of range, so a client never mistakes a saturated
    reading for a good one even though the clamped counts equal the fault codes.
    The status is None when the map's channel has no status field.
    """
    faults = layout.faults
    status_codes = faults.status_codes if faults is not None else {"ok": 0}
    value_codes = faults.value_codes if faults is not None else {}

    def status_of(status: ChannelStatus) -> int:
        return status_codes.get(status.name.lower(), int(status))

    status = ChannelStatus.OPEN_CIRCUIT if reading is None else ChannelStatus(reading.status)
    if status in (ChannelStatus.OPEN_CIRCUIT, ChannelStatus.SHORT_CIRCUIT):
        code = value_codes.get(status.name.lower())
        raw = code if code is not None else channel.raw(math.nan)[0]
    else:
        assert reading is not None
        raw, clamped = channel.raw(reading.value_C)
        if clamped or math.isnan(reading.value_C):
            status = ChannelStatus.OUT_OF_RANGE
    return raw, (status_of(status) if channel.status is not None else None)


def encode_temperature(
    reading: ChannelReading | None, layout: DeviceRegisters | None = None, channel: int = 0
) -> tuple[int, int]:
    """One channel of a one-register map (by default the Pt100 module) → (value, status) words."""
    layout = layout if layout is not None else pt100_layout()
    codec = layout.channels[channel]
    raw, status = encode_channel(layout, codec, reading)
    (value,) = layout.encode_block([codec], {codec.name: raw})
    if codec.status is None or status is None:
        raise ValueError(f"channel {channel + 1} of {layout.map.label} has no status field")
    status_codec = layout.fields[codec.status]
    (status_word,) = layout.encode_block([status_codec], {status_codec.name: status})
    return value, status_word


@cache
def pt100_layout() -> DeviceRegisters:
    """The shipped 8-channel Pt100 module's map, ready for the wire."""
    return DeviceRegisters(load_register_map(TRANSMITTER_MAP))


def bit_table_placeholders() -> tuple[list[SimData], list[SimData]]:
    """Coil and discrete-input blocks for a ``SimDevice`` 4-tuple.

    pymodbus needs a non-empty block for each of the four tables before it keeps
    holding and input registers apart; our devices have no bits, so the action
    refuses every bit function code on these placeholders.
    """
    return [SimData(0, datatype=DataType.BITS)], [SimData(0, datatype=DataType.BITS)]


def is_internal_write(function_code: int, values: object) -> bool:
    """True for the server's own ``async_setValues`` calls made by ``publish()``.

    No client can send values with a read function code (3, 4), so ``publish()`` stores
    with those codes and the action tells its own updates from a client's writes.
    """
    return values is not None and function_code in (3, 4)


@dataclass(frozen=True)
class ReceivedRequest:
    """One request a simulated device answered: when (monotonic s), what, where, how many."""

    at_s: float
    device_id: int
    function_code: int
    address: int
    count: int


def known_devices_only(
    device_ids: Collection[int],
    silenced: Collection[int] = frozenset(),
    received: deque[ReceivedRequest] | None = None,
) -> Callable[[bool, ModbusPDU], ModbusPDU]:
    """A pymodbus ``trace_pdu`` hook that drops requests for device ids nobody has.

    On an RS-485 bus a request to an absent slave (or a broadcast to read-only modules)
    gets no answer at all; pymodbus would instead answer with an exception and log a
    traceback. Returning no PDU makes the request handler skip the request, so clients
    see the same timeout as on a real bus. ``silenced`` (a live collection the
    caller may change) makes present devices fall silent too, as a slave that lost
    power or its cable does. Every request that is let through is appended to
    ``received`` (a bounded deque), so a test can count what a client sent.
    """
    known = frozenset(device_ids)

    def trace_pdu(sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if sending:
            return pdu
        if pdu.dev_id not in known or pdu.dev_id in silenced:
            return cast(ModbusPDU, None)
        if received is not None:
            count = getattr(pdu, "count", 0)
            address = getattr(pdu, "address", 0)
            received.append(
                ReceivedRequest(time.monotonic(), pdu.dev_id, pdu.function_code, address, count)
            )
        return pdu

    return trace_pdu


class ModbusEndpoint:
    """Life cycle shared by the simulator's Modbus slaves: start, publish, stop.

    Subclasses build the pymodbus server (which needs a running event loop, so it is
    made in ``start()``, never in a constructor) and fill its registers in ``publish()``.
    The registers are filled before the server listens, so the first request a client
    sends is already answered with the machine's values.
    """

    def __init__(self) -> None:
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        #: The latest requests the server let through (oldest dropped), for tests.
        self.received: deque[ReceivedRequest] = deque(maxlen=RECEIVED_KEPT)

    def _make_server(self) -> ModbusTcpServer | ModbusSerialServer:
        raise NotImplementedError

    def _describe(self) -> str:
        raise NotImplementedError

    async def publish(self) -> None:
        raise NotImplementedError

    @property
    def running(self) -> bool:
        """True between a successful ``start()`` and ``stop()``."""
        return self._server is not None

    def _require_server(self) -> ModbusTcpServer | ModbusSerialServer:
        if self._server is None:
            raise RuntimeError(f"{self._describe()} is not started")
        return self._server

    async def start(self) -> None:
        """Build the register image, publish the current snapshot, then listen."""
        if self._server is not None:
            raise RuntimeError(f"{self._describe()} is already started")
        server = self._server = self._make_server()
        try:
            await self.publish()
        except BaseException:
            await self._discard_server()
            raise
        try:
            await server.serve_forever(background=True)
        except RuntimeError as exc:  # pymodbus: "Could not start listen, please check address."
            await self._discard_server()
            raise OSError(f"{self._describe()}: cannot listen ({exc})") from exc
        except BaseException:
            await self._discard_server()
            raise

    async def stop(self) -> None:
        """Stop listening and drop client connections; a no-op when not started."""
        await self._discard_server()

    async def _discard_server(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            await server.shutdown()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *_exc: object) -> None:
        await self.stop()

    def _bound_tcp_address(self, requested: tuple[str, int]) -> tuple[str, int]:
        """The address actually listened on (the real port when port 0 was requested)."""
        server = self._server
        sockets = getattr(server.transport, "sockets", None) if server is not None else None
        if not sockets:
            return requested
        host, port = sockets[0].getsockname()[:2]
        return str(host), int(port)
