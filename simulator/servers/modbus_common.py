"""Shared pieces of the simulator's Modbus slaves: temperature encoding and pymodbus plumbing.

The register codecs the gateway's clients also use are in ``drivers.register_codec``;
the channel encoder here is a pure function so that the exact bit patterns a real
device would put on the wire (fault codes, clamping) are unit-tested without a socket.
The plumbing wraps pymodbus 3.16's ``SimDevice`` model, whose only hook into a
request is the device ``action`` coroutine; both servers build on it the same way.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Coroutine
from typing import Self, cast

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData

from drivers.register_codec import (
    INT16_MAX,
    INT16_MIN,
    OPEN_CIRCUIT_CODE,
    SHORT_CIRCUIT_CODE,
    int16_to_register,
)
from simulator.link import ChannelReading, ChannelStatus

#: Function codes a Modbus client uses to write holding registers.
WRITE_FUNCTION_CODES = frozenset({6, 16, 22, 23})
#: Function codes that address bits (coils, discrete inputs): none of our devices has any.
BIT_FUNCTION_CODES = frozenset({1, 2, 5, 15})

#: Signature of a pymodbus ``SimDevice`` action (see pymodbus.simulator.SimAction).
Action = Callable[
    [int, int, int, int, list[int], list[int] | list[bool] | None],
    Coroutine[None, None, ExcCodes | None],
]


def encode_temperature(reading: ChannelReading | None) -> tuple[int, int]:
    """One transmitter channel → (value register, status register), as a Pt100 module shows it.

    Counts are 0.1 °C, rounded to the nearest count, ties away from zero so that
    +x.x5 °C and −x.x5 °C stay symmetric. ``None`` is a channel without a
    probe attached: a real module sees an open input, so it reports the open-circuit
    code and status. A value that does not fit int16 (or is not a number) is clamped
    and flagged OUT_OF_RANGE, so a client never mistakes a saturated reading for a
    good one even though the clamped counts equal the fault codes.
    """
    if reading is None or reading.status == ChannelStatus.OPEN_CIRCUIT:
        return int16_to_register(OPEN_CIRCUIT_CODE), int(ChannelStatus.OPEN_CIRCUIT)
    if reading.status == ChannelStatus.SHORT_CIRCUIT:
        return int16_to_register(SHORT_CIRCUIT_CODE), int(ChannelStatus.SHORT_CIRCUIT)
    status = ChannelStatus(reading.status)
    value = reading.value_C
    if math.isnan(value):
        return int16_to_register(INT16_MAX), int(ChannelStatus.OUT_OF_RANGE)
    counts = value * 10.0
    if counts > INT16_MAX:
        return int16_to_register(INT16_MAX), int(ChannelStatus.OUT_OF_RANGE)
    if counts < INT16_MIN:
        return int16_to_register(INT16_MIN), int(ChannelStatus.OUT_OF_RANGE)
    nearest = int(math.copysign(math.floor(abs(counts) + 0.5), counts))  # ties away from 0
    return int16_to_register(nearest), int(status)


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


def known_devices_only(
    device_ids: Collection[int], silenced: Collection[int] = frozenset()
) -> Callable[[bool, ModbusPDU], ModbusPDU]:
    """A pymodbus ``trace_pdu`` hook that drops requests for device ids nobody has.

    On an RS-485 bus a request to an absent slave (or a broadcast to read-only modules)
    gets no answer at all; pymodbus would instead answer with an exception and log a
    traceback. Returning no PDU makes the request handler skip the request, so clients
    see the same timeout as on a real bus. ``silenced`` (a live collection the
    caller may change) makes present devices fall silent too, as a slave that lost
    power or its cable does.
    """
    known = frozenset(device_ids)

    def trace_pdu(sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if not sending and (pdu.dev_id not in known or pdu.dev_id in silenced):
            return cast(ModbusPDU, None)
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
