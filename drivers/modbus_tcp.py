"""A lean Modbus TCP client: one asyncio protocol per connection, requests run as chains.

pymodbus's client runs every request through its transaction manager: a request
object, a lock, an ``asyncio.wait_for`` (a future, a timer and callbacks), the
transport's debug dump and a reply object with one ``struct.unpack`` per register.
At a thousand machines that is most of the poll's CPU, more than the socket
calls themselves. Here the request PDUs are still built by pymodbus's own request
classes (once per request shape, :func:`read_step`), and any reply other than
registers is decoded by the caller with pymodbus's decoder; the MBAP framing
(seven header bytes) is done here.

A caller hands :meth:`TcpTransactions.submit` a whole *chain*: the reads of one or
more devices (each device a group of requests, one per contiguous block of its
register map). The protocol puts the first request on the wire; each reply is
parsed in ``data_received``, which writes the next request at once, without a
task wake-up in between. The chain's one future is resolved when its last reply
is in, with one outcome per group (the registers, or why there are none). So a
cycle's reads of one connection cost one future and at most one timer, however
many requests they are.

The rules a real device needs are kept:

* strictly one request on the wire per connection: a chain submitted while
  another runs waits in a queue and starts from the reply that ends the other
  (many devices and serial gateways, and pymodbus's own server, answer only the
  first of two requests sent together);
* each request has its own timeout, ``timeout_s`` from its send: one deadline per
  connection, moved on by each send, and one timer that looks at it when it
  fires (re-armed only if the deadline moved past it), cancelled when the
  connection falls idle: one timer per chain instead of one per request; a
  timed-out request is sent again ``retries`` times with a fresh transaction
  id, then its group fails with ``TimeoutError`` and the chain goes on with the
  next group (one silent device does not fail the others);
* a reply whose transaction id or device id is not the waiting request's is
  dropped (a late reply after a timeout, another device's reply), as pymodbus
  drops it; a frame with another protocol id than Modbus's 0 means the stream is
  out of step, and the connection is closed;
* a lost connection fails the group in progress and every later one with
  ``ConnectionError``; the groups already read keep their registers;
* exception 06 (slave device busy: the device did not act on the request, and
  asks to be asked again) is retried after a short back-off, up to
  ``len(BUSY_BACKOFF_S)`` times per request, within the cycle; the request's
  timeout starts again at each resend. Counted in ``busy_retries``. A device
  that is still busy after that fails its group with the exception reply.

Errors are the builtin ones (``ConnectionError``, ``TimeoutError``, ``ValueError``
for a reply of the wrong length, :class:`ReplyError` for a reply that is not
registers); :class:`drivers.transmitters.ModbusConnection` turns them into the
gateway's.
"""

from __future__ import annotations

import asyncio
import struct
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import cast

from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    WriteMultipleRegistersRequest,
)

#: Function codes read here without building a reply object: FC3 and FC4.
READ_FUNCTIONS = {3: ReadHoldingRegistersRequest, 4: ReadInputRegistersRequest}
#: Transaction ids are 16 bits; 0 is left out so a stray zero never matches.
_TID_SPAN = 0xFFFF
#: An MBAP header (transaction, protocol, length, unit) and a function code.
_MIN_FRAME = 8
#: Modbus exception 06, slave device busy.
DEVICE_BUSY = 0x06
#: Waits before asking a busy device again (50 ms in all: well within a 1 s cycle).
BUSY_BACKOFF_S = (0.005, 0.015, 0.03)


@cache
def read_pdu(function_code: int, address: int, count: int) -> bytes:
    """Function code and body of a register read, built once by pymodbus's request class."""
    request = READ_FUNCTIONS[function_code](address=address, count=count)
    return bytes((function_code,)) + request.encode()


def write_pdu(address: int, values: list[int]) -> bytes:
    """Function code and body of an FC16 write (pymodbus's request class checks the values)."""
    request = WriteMultipleRegistersRequest(address=address, registers=values)
    return bytes((16,)) + request.encode()


@dataclass(frozen=True, slots=True)
class Step:
    """One request of a chain, ready for the wire but for its transaction id.

    ``tail`` is the frame after the transaction id (protocol id, length, unit id,
    PDU). ``count`` > 0: a register read, whose outcome is ``count`` registers;
    ``count`` 0: any reply PDU is the outcome, as bytes (a write's echo).
    """

    tail: bytes
    device_id: int
    count: int
    registers: struct.Struct | None


def step(pdu: bytes, device_id: int, count: int = 0) -> Step:
    """A chain step sending ``pdu`` to ``device_id`` (``count`` registers expected, or 0)."""
    if not 0 <= device_id <= 255:
        raise ValueError(f"device id {device_id} is outside 0–255")
    tail = b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big") + bytes((device_id,)) + pdu
    return Step(tail, device_id, count, struct.Struct(f">{count}H") if count else None)


@cache
def read_step(function_code: int, address: int, count: int, device_id: int) -> Step:
    """The step of one FC3/FC4 read, built once per shape (a gateway reads the same ones)."""
    return step(read_pdu(function_code, address, count), device_id, count)


class ReplyError(Exception):
    """The device answered, but not with registers (an exception reply, mostly).

    ``pdu`` is the reply, for pymodbus's decoder to say what it means.
    """

    def __init__(self, pdu: bytes) -> None:
        super().__init__(pdu.hex())
        self.pdu = pdu


#: One group's outcome: its registers (or a ``count`` 0 step's reply PDU), or why not.
Outcome = list[int] | bytes | BaseException


class _Chain:
    """A submitted chain: its groups, where it is, what came back so far."""

    __slots__ = (
        "attempt",
        "busy",
        "future",
        "group",
        "groups",
        "index",
        "outcomes",
        "registers",
        "retries",
        "step",
        "tid",
        "timeout_s",
    )

    def __init__(
        self,
        groups: Sequence[Sequence[Step]],
        timeout_s: float,
        retries: int,
        future: asyncio.Future[list[Outcome]],
    ) -> None:
        self.groups = groups
        self.timeout_s = timeout_s
        self.retries = retries
        self.future = future
        self.outcomes: list[Outcome] = []
        self.group = 0
        self.index = 0
        self.step = groups[0][0]
        self.attempt = 0
        self.busy = 0  # busy replies to the current step
        self.tid = 0
        self.registers: list[int] = []


class TcpTransactions(asyncio.Protocol):
    """One Modbus TCP connection running chains of requests, one request on the wire at a time.

    See the module's docstring for the rules. The constructor needs a running loop.
    """

    def __init__(self) -> None:
        self._transport: asyncio.Transport | None = None
        self._buffer = b""
        self._active: _Chain | None = None
        self._queue: deque[_Chain] = deque()
        self._tid = 0
        self._lost: str | None = None
        self._loop = asyncio.get_running_loop()
        #: The request on the wire has no answer by this loop time.
        self._deadline = 0.0
        #: Requests sent again after a busy reply (exception 06), since the connection.
        self.busy_retries = 0
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = 0.0

    # -- asyncio.Protocol -------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # No isinstance check: uvloop's transports have asyncio.Transport's methods
        # without deriving from it.
        self._transport = cast(asyncio.Transport, transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._lost is None:
            self._lost = f"connection lost ({exc})" if exc else "connection lost"
        self._transport = None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        chains = [] if self._active is None else [self._active]
        chains += self._queue
        self._active = None
        self._queue.clear()
        for chain in chains:
            if chain.future.done():
                continue
            outcomes = chain.outcomes
            while len(outcomes) < len(chain.groups):
                outcomes.append(ConnectionError(self._lost))
            chain.future.set_result(outcomes)

    def data_received(self, data: bytes) -> None:
        buffer = self._buffer + data if self._buffer else data
        size = len(buffer)
        start = 0
        while size - start >= _MIN_FRAME:
            if buffer[start + 2] or buffer[start + 3]:  # not Modbus: the stream is out of step
                self._buffer = b""
                self.close()
                return
            end = start + 6 + ((buffer[start + 4] << 8) | buffer[start + 5])
            if end > size:
                break
            chain = self._active
            if (
                chain is not None
                and end > start + 7
                and (buffer[start] << 8) | buffer[start + 1] == chain.tid
                and buffer[start + 6] == chain.step.device_id
            ):
                self._reply(chain, buffer[start + 7 : end])
            start = end
        self._buffer = buffer[start:] if start < size else b""

    # -- chains -----------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        transport = self._transport
        return transport is not None and not transport.is_closing()

    def submit(
        self, groups: Sequence[Sequence[Step]], timeout_s: float, retries: int = 0
    ) -> asyncio.Future[list[Outcome]]:
        """Run ``groups`` (each a non-empty sequence of steps) in turn, after any chain
        already submitted. The future gets one :data:`Outcome` per group; it never
        raises. Cancelling it stops the chain at its request on the wire."""
        transport = self._transport
        if transport is None or transport.is_closing():
            raise ConnectionError(self._lost or "connection lost")
        chain = _Chain(groups, timeout_s, retries, self._loop.create_future())
        if self._active is None:
            self._active = chain
            self._send(chain)
        else:
            self._queue.append(chain)
        return chain.future

    def close(self) -> None:
        transport, self._transport = self._transport, None
        if transport is not None:
            transport.close()
        self.connection_lost(None)

    def _send(self, chain: _Chain) -> None:
        """Put the chain's current step on the wire with a fresh transaction id."""
        tid = self._tid % _TID_SPAN + 1
        self._tid = chain.tid = tid
        deadline = self._deadline = self._loop.time() + chain.timeout_s
        timer = self._timer
        if timer is None or deadline < self._timer_at:
            if timer is not None:
                timer.cancel()
            self._timer_at = deadline
            self._timer = self._loop.call_at(deadline, self._on_timer)
        transport = self._transport
        if transport is not None:  # else the connection is going: connection_lost ends it
            transport.write(tid.to_bytes(2, "big") + chain.step.tail)

    def _reply(self, chain: _Chain, pdu: bytes) -> None:
        """The reply to the chain's request on the wire."""
        if chain.future.done():  # cancelled: the chain ends here
            self._next_chain()
            return
        current = chain.step
        count = current.count
        busy = pdu[0] & 0x80 and pdu[1:2] == bytes((DEVICE_BUSY,))
        if busy and chain.busy < len(BUSY_BACKOFF_S):
            self._ask_again(chain)
        elif not count:
            self._group_done(chain, pdu)
        elif pdu[0] & 0x80:
            self._group_done(chain, ReplyError(pdu))
        elif len(pdu) != 2 + 2 * count or pdu[1] != 2 * count:
            self._group_done(
                chain, ValueError(f"{(len(pdu) - 2) // 2} registers in the reply, {count} asked")
            )
        else:
            assert current.registers is not None
            chain.registers += current.registers.unpack_from(pdu, 2)
            group = chain.groups[chain.group]
            if chain.index + 1 < len(group):
                chain.index += 1
                chain.step = group[chain.index]
                chain.attempt = chain.busy = 0
                self._send(chain)
                return
            registers, chain.registers = chain.registers, []
            self._group_done(chain, registers)

    def _ask_again(self, chain: _Chain) -> None:
        """The device is busy: send the same request again after a back-off. Nothing is
        on the wire meanwhile; the deadline moves past the resend, so the timer waits."""
        delay_s = BUSY_BACKOFF_S[chain.busy]
        chain.busy += 1
        self.busy_retries += 1
        self._deadline = self._loop.time() + delay_s + chain.timeout_s
        self._loop.call_later(delay_s, self._resend, chain)

    def _resend(self, chain: _Chain) -> None:
        if chain is not self._active or self._transport is None:
            return  # the connection went, or the chain ended, during the back-off
        if chain.future.done():  # cancelled during the back-off
            self._next_chain()
            return
        self._send(chain)

    def _group_done(self, chain: _Chain, outcome: Outcome) -> None:
        """The current group is over: on to the next group, or the chain is done."""
        chain.outcomes.append(outcome)
        chain.registers = []
        chain.group += 1
        if chain.group < len(chain.groups):
            chain.index = 0
            chain.attempt = chain.busy = 0
            chain.step = chain.groups[chain.group][0]
            self._send(chain)
            return
        chain.future.set_result(chain.outcomes)
        self._next_chain()

    def _next_chain(self) -> None:
        """Nothing of the active chain is on the wire any more: start the next one."""
        self._active = None
        queue = self._queue
        while queue:
            chain = queue.popleft()
            if not chain.future.done():
                self._active = chain
                self._send(chain)
                return
        timer = self._timer  # idle: a cancel costs less than letting it fire
        if timer is not None:
            self._timer = None
            timer.cancel()

    def _on_timer(self) -> None:
        """The deadline timer: re-armed if the deadline moved on, else a timeout."""
        self._timer = None
        chain = self._active
        if chain is None:
            return
        deadline = self._deadline
        if self._loop.time() < deadline:
            self._timer_at = deadline
            self._timer = self._loop.call_at(deadline, self._on_timer)
            return
        if chain.future.done():  # cancelled, and its request is now given up on
            self._next_chain()
            return
        if chain.attempt < chain.retries:
            chain.attempt += 1
            self._send(chain)
            return
        self._group_done(chain, TimeoutError())


async def connect(host: str, port: int, timeout_s: float) -> TcpTransactions:
    """A connected :class:`TcpTransactions` (``OSError`` or ``TimeoutError`` if not)."""
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(timeout_s):
        _, protocol = await loop.create_connection(TcpTransactions, host, port)
    return protocol
