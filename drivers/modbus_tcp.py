"""A lean Modbus TCP client: pymodbus's framer and PDUs on one asyncio protocol.

pymodbus's client runs every request through its transaction manager: a request
object, a lock, an ``asyncio.wait_for`` (a future, a timer and callbacks), the
transport's debug dump and a reply object with one ``struct.unpack`` per register.
At a thousand machines that is most of the poll's CPU, more than the socket
calls themselves. :class:`TcpTransactions` keeps the library's wire format
(``FramerSocket`` splits and builds the MBAP frames, the request PDUs are
pymodbus's own classes; the caller decodes any reply other than a register read
with pymodbus's client decoder) and drops the rest: one asyncio protocol per
connection, a map of pending transaction ids, one timer per request.

Replies are matched by transaction id, so a late reply to a request that timed
out is never taken for the next one's: :meth:`TcpTransactions.send` puts a
request on the wire and returns its pending reply.
Errors are the builtin ones (``ConnectionError``, ``TimeoutError``,
``ValueError`` for a malformed reply); :class:`drivers.transmitters.ModbusConnection`
turns them into the gateway's.
"""

from __future__ import annotations

import asyncio
import struct
from dataclasses import dataclass
from functools import cache
from typing import cast

from pymodbus.framer import FramerSocket
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    WriteMultipleRegistersRequest,
)

#: Function codes read here without building a reply object: FC3 and FC4.
READ_FUNCTIONS = {3: ReadHoldingRegistersRequest, 4: ReadInputRegistersRequest}
#: Transaction ids are 16 bits; 0 is left out so a stray zero never matches.
_TID_SPAN = 0xFFFF


@cache
def _registers_struct(count: int) -> struct.Struct:
    return struct.Struct(f">{count}H")


@cache
def read_pdu(function_code: int, address: int, count: int) -> bytes:
    """Function code and body of a register read, built once by pymodbus's request class."""
    request = READ_FUNCTIONS[function_code](address=address, count=count)
    return bytes((function_code,)) + request.encode()


def write_pdu(address: int, values: list[int]) -> bytes:
    """Function code and body of an FC16 write (pymodbus's request class checks the values)."""
    request = WriteMultipleRegistersRequest(address=address, registers=values)
    return bytes((16,)) + request.encode()


def decode_registers(pdu: bytes, count: int) -> list[int]:
    """The registers of an FC3/FC4 reply PDU; ``ValueError`` when its length is wrong."""
    if len(pdu) != 2 + 2 * count or pdu[1] != 2 * count:
        raise ValueError(f"{(len(pdu) - 2) // 2} registers in the reply, {count} asked")
    return list(_registers_struct(count).unpack_from(pdu, 2))


@dataclass(slots=True)
class Pending:
    """One request on the wire: its reply future, its device, its timer."""

    tid: int
    device_id: int
    future: asyncio.Future[bytes]
    timer: asyncio.TimerHandle


class TcpTransactions(asyncio.Protocol):
    """One Modbus TCP connection: frames out, replies matched to their transaction ids.

    A reply whose device id is not the request's is dropped, as pymodbus drops it
    (the request then times out); a reply for an id nobody waits for (a late
    reply after its timeout) is dropped too. A frame with another protocol id
    than Modbus's 0 means the stream is out of step: the connection is closed.
    """

    def __init__(self) -> None:
        self._framer = FramerSocket(DecodePDU(False))
        self._transport: asyncio.Transport | None = None
        self._buffer = b""
        self._pending: dict[int, Pending] = {}
        self._tid = 0
        self._lost: str | None = None
        self._loop = asyncio.get_running_loop()

    # -- asyncio.Protocol -------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # No isinstance check: uvloop's transports have asyncio.Transport's methods
        # without deriving from it.
        self._transport = cast(asyncio.Transport, transport)

    def connection_lost(self, exc: Exception | None) -> None:
        self._lost = f"connection lost ({exc})" if exc else "connection lost"
        self._transport = None
        pending, self._pending = self._pending, {}
        for request in pending.values():
            request.timer.cancel()
            if not request.future.done():
                request.future.set_exception(ConnectionError(self._lost))

    def data_received(self, data: bytes) -> None:
        buffer = self._buffer + data if self._buffer else data
        decode = self._framer.decode
        while len(buffer) >= FramerSocket.MIN_SIZE:
            used, device_id, tid, pdu = decode(buffer)
            if not used:
                if buffer[2:4] != b"\x00\x00":  # not Modbus: the stream is out of step
                    self.close()
                    return
                break
            buffer = buffer[used:]
            request = self._pending.get(tid)
            if request is None or request.device_id != device_id or not pdu:
                continue
            del self._pending[tid]
            request.timer.cancel()
            if not request.future.done():
                request.future.set_result(pdu)
        self._buffer = buffer

    # -- requests ---------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        transport = self._transport
        return transport is not None and not transport.is_closing()

    def send(self, pdu: bytes, device_id: int, timeout_s: float) -> Pending:
        """Put one request on the wire. Its ``future`` gets the reply PDU, or
        ``TimeoutError`` after ``timeout_s``, or ``ConnectionError`` when the connection
        goes; the caller then hands it to :meth:`forget`."""
        transport = self._transport
        if transport is None or transport.is_closing():
            raise ConnectionError(self._lost or "connection lost")
        tid = self._next_tid()
        future: asyncio.Future[bytes] = self._loop.create_future()
        timer = self._loop.call_later(timeout_s, self._expire, tid, future)
        request = Pending(tid, device_id, future, timer)
        self._pending[tid] = request
        transport.write(self._framer.encode(pdu, device_id, tid))
        return request

    def forget(self, request: Pending) -> None:
        """``request`` is done with (answered, timed out or cancelled): stop its timer."""
        if self._pending.get(request.tid) is request:
            del self._pending[request.tid]
        request.timer.cancel()

    def close(self) -> None:
        transport, self._transport = self._transport, None
        if transport is not None:
            transport.close()
        self.connection_lost(None)

    def _expire(self, tid: int, future: asyncio.Future[bytes]) -> None:
        request = self._pending.get(tid)
        if request is not None and request.future is future:
            del self._pending[tid]
        if not future.done():
            future.set_exception(TimeoutError())

    def _next_tid(self) -> int:
        for _ in range(_TID_SPAN):
            self._tid = self._tid % _TID_SPAN + 1
            if self._tid not in self._pending:
                return self._tid
        raise ConnectionError("every transaction id is in use")


async def connect(host: str, port: int, timeout_s: float) -> TcpTransactions:
    """A connected :class:`TcpTransactions` (``OSError`` or ``TimeoutError`` if not)."""
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(timeout_s):
        _, protocol = await loop.create_connection(TcpTransactions, host, port)
    return protocol
