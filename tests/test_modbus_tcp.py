"""The lean Modbus TCP client (drivers.modbus_tcp) against a scripted server on loopback.

The scripted server is a real TCP server that answers each request as the test
tells it: late, with an exception, with another device id, or by hanging up. It
checks what pymodbus's servers cannot provoke on demand: a late reply to a
timed-out request is never taken for the next request's reply.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from drivers.modbus_tcp import read_step
from drivers.transmitters import (
    ModbusConnection,
    ModbusLinkLostError,
    ModbusNoResponseError,
    ModbusRefusedError,
)

HOST = "127.0.0.1"
#: Generous for a loaded machine: only the deliberately late reply is meant to miss it.
TIMEOUT_S = 1.0

#: How the server answers the n-th request (0-based): (delay s, reply PDU or None, device id).
Script = Callable[[int, bytes], tuple[float, bytes | None, int | None]]


def registers_pdu(function_code: int, values: list[int]) -> bytes:
    return bytes((function_code, 2 * len(values))) + struct.pack(f">{len(values)}H", *values)


class ScriptedServer:
    """Answers each Modbus TCP frame after a delay, with what the script says."""

    def __init__(self, script: Script) -> None:
        self._script = script
        self.requests: list[bytes] = []
        #: Requests read but not answered yet, and the most there ever were at once.
        self.outstanding = 0
        self.most_outstanding = 0
        self._server: asyncio.Server | None = None

    async def __aenter__(self) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._serve, HOST, 0)
        return HOST, self._server.sockets[0].getsockname()[1]

    async def __aexit__(self, *_: object) -> None:
        assert self._server is not None
        self._server.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                header = await reader.readexactly(7)
                body = await reader.readexactly(int.from_bytes(header[4:6], "big") - 1)
                index = len(self.requests)
                self.requests.append(header + body)
                self.outstanding += 1
                self.most_outstanding = max(self.most_outstanding, self.outstanding)
                delay_s, pdu, device_id = self._script(index, body)
                if pdu is None:
                    writer.close()
                    return
                asyncio.get_running_loop().call_later(
                    delay_s, self._reply, writer, header, pdu, device_id
                )
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.close()

    def _reply(
        self, writer: asyncio.StreamWriter, header: bytes, pdu: bytes, device_id: int | None
    ) -> None:
        self.outstanding -= 1
        if writer.is_closing():
            return
        unit = header[6] if device_id is None else device_id
        writer.write(header[0:4] + (len(pdu) + 1).to_bytes(2, "big") + bytes((unit,)) + pdu)


def run(body: Callable[[], object]) -> None:
    asyncio.run(asyncio.wait_for(body(), 60))  # type: ignore[arg-type]


@contextlib.asynccontextmanager
async def opened(server: ScriptedServer, **options: Any) -> AsyncIterator[ModbusConnection]:
    """A connection to ``server`` (started here, stopped on the way out), open."""
    async with server as address:
        link = ModbusConnection(tcp=address, **options)
        await link.open()
        try:
            yield link
        finally:
            link.close()


def test_a_late_reply_is_never_taken_for_the_next_request() -> None:
    """Request 0 is answered after its timeout; request 1 must get its own registers."""

    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        delay_s = TIMEOUT_S + 0.5 if index == 0 else 0.0
        return delay_s, registers_pdu(body[0], [100 + index, 7]), None

    async def body() -> None:
        async with opened(ScriptedServer(script), timeout_s=TIMEOUT_S) as link:
            with pytest.raises(ModbusNoResponseError, match="no response from device 3"):
                await link.read_input_registers(0, 2, device_id=3)
            assert await link.read_holding_registers(0, 2, device_id=3) == [101, 7]
            await asyncio.sleep(0.7)  # the late reply to request 0 arrives meanwhile
            assert await link.read_holding_registers(0, 2, device_id=3) == [102, 7]
            assert link.connected

    run(body)


def test_retries_send_the_request_again() -> None:
    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        delay_s = 10.0 if index == 0 else 0.0  # the first attempt is never answered in time
        return delay_s, registers_pdu(body[0], [index]), None

    async def body() -> None:
        server = ScriptedServer(script)
        async with opened(server, timeout_s=1.0, retries=1) as link:
            assert await link.read_holding_registers(5, 1, device_id=1) == [1]
            assert len(server.requests) == 2
            tids = {request[0:2] for request in server.requests}
            assert len(tids) == 2  # a fresh transaction id for the second attempt

    run(body)


def test_exception_replies_a_foreign_device_and_a_hang_up() -> None:
    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        if index == 0:
            return 0.0, bytes((body[0] | 0x80, 2)), None  # illegal data address
        if index == 1:
            return 0.0, bytes((body[0] | 0x80, 0x0B)), None  # gateway: target did not answer
        if index == 2:
            return 0.0, registers_pdu(body[0], [1, 2]), 9  # another device's reply: dropped
        if index == 3:
            return 0.0, bytes((16,)) + body[1:5], None  # FC16 echo
        if index == 4:
            return 0.0, registers_pdu(body[0], [1]), None  # one register, two asked
        return 0.0, None, None  # hang up

    async def body() -> None:
        async with opened(ScriptedServer(script), timeout_s=1.0) as link:
            with pytest.raises(ModbusRefusedError, match="exception 2") as refused:
                await link.read_holding_registers(0, 2, device_id=1)
            assert refused.value.code == 2
            with pytest.raises(ModbusNoResponseError, match="gateway exception 0x0b"):
                await link.read_holding_registers(0, 2, device_id=1)
            with pytest.raises(ModbusNoResponseError, match="no response from device 1"):
                await link.read_holding_registers(0, 2, device_id=1)
            await link.write_registers(1000, [0x3C4C, 0xCCCD], device_id=1)
            with pytest.raises(ModbusNoResponseError, match="1 registers in the reply, 2"):
                await link.read_input_registers(0, 2, device_id=1)
            with pytest.raises(ModbusLinkLostError, match="connection lost"):
                await link.read_input_registers(0, 2, device_id=1)
            assert not link.connected

    run(body)


# -- chains: several devices' reads sent one after the other from the replies ----------


def unit_of(request: bytes) -> int:
    return request[6]


def test_a_chain_reads_every_group_and_keeps_one_request_on_the_wire() -> None:
    """Two devices of two blocks each, and a second chain submitted while the first runs:
    every reply lands in its group, and the server never has two requests at once."""

    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        address = int.from_bytes(body[1:3], "big")
        return 0.01, registers_pdu(body[0], [address, index]), None

    chain = (
        (read_step(4, 0, 2, 1), read_step(4, 8, 2, 1)),
        (read_step(3, 100, 2, 2), read_step(3, 200, 2, 2)),
    )

    async def body() -> None:
        server = ScriptedServer(script)
        async with opened(server, timeout_s=TIMEOUT_S) as link:
            first, second = await asyncio.gather(link.read_chain(chain), link.read_chain(chain[1:]))
            assert first == [[0, 0, 8, 1], [100, 2, 200, 3]]
            assert second == [[100, 4, 200, 5]]
            assert [unit_of(r) for r in server.requests] == [1, 1, 2, 2, 2, 2]
            assert server.most_outstanding == 1

    run(body)


def test_a_timeout_mid_chain_fails_that_device_only_and_its_late_reply_is_dropped() -> None:
    """Device 1's second block is answered after its timeout, while device 2's request is
    on the wire: device 1 fails with the timeout, device 2 gets its own registers."""
    timeout_s = 0.4

    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        if index == 1:  # device 1, second block: late, arrives while device 2 waits
            return timeout_s + 0.15, registers_pdu(body[0], [666, 666]), None
        if index == 2:  # device 2: answered after the late reply came in
            return 0.3, registers_pdu(body[0], [20, 21]), None
        return 0.0, registers_pdu(body[0], [10 + index, 0]), None

    chain = ((read_step(4, 0, 2, 1), read_step(4, 8, 2, 1)), (read_step(4, 0, 2, 2),))

    async def body() -> None:
        server = ScriptedServer(script)
        async with opened(server, timeout_s=timeout_s) as link:
            started = asyncio.get_running_loop().time()
            device_1, device_2 = await link.read_chain(chain)
            elapsed_s = asyncio.get_running_loop().time() - started
            assert isinstance(device_1, ModbusNoResponseError)
            assert "no response from device 1" in str(device_1)
            assert device_2 == [20, 21]
            # uvloop's timers are kept in whole milliseconds: each of the two waits
            # may end up to 1 ms before its nominal time.
            assert timeout_s + 0.3 - 0.002 <= elapsed_s < timeout_s + 0.3 + TIMEOUT_S
            assert link.connected
            assert await link.read_input_registers(0, 2, device_id=2) == [13, 0]

    run(body)


def test_retries_in_a_chain_send_the_request_again_with_a_fresh_transaction_id() -> None:
    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        delay_s = 10.0 if index == 1 else 0.0  # device 2's first attempt is never answered
        return delay_s, registers_pdu(body[0], [index]), None

    chain = ((read_step(3, 0, 1, 1),), (read_step(3, 0, 1, 2),), (read_step(3, 0, 1, 3),))

    async def body() -> None:
        server = ScriptedServer(script)
        async with opened(server, timeout_s=0.3, retries=1) as link:
            assert await link.read_chain(chain) == [[0], [2], [3]]
            assert [unit_of(r) for r in server.requests] == [1, 2, 2, 3]
            assert len({r[0:2] for r in server.requests}) == 4

    run(body)


def test_a_reply_from_another_device_is_dropped_and_the_chain_goes_on() -> None:
    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        if index == 0:  # device 1's request answered by device 9: not its reply
            return 0.0, registers_pdu(body[0], [99, 99]), 9
        if index == 1:
            return 0.0, bytes((body[0] | 0x80, 2)), None  # device 2: illegal data address
        return 0.0, registers_pdu(body[0], [30 + index, 1]), None

    chain = ((read_step(4, 0, 2, 1),), (read_step(4, 0, 2, 2),), (read_step(4, 0, 2, 3),))

    async def body() -> None:
        async with opened(ScriptedServer(script), timeout_s=0.4) as link:
            device_1, device_2, device_3 = await link.read_chain(chain)
            assert isinstance(device_1, ModbusNoResponseError)
            assert "no response from device 1" in str(device_1)
            assert isinstance(device_2, ModbusRefusedError)
            assert device_2.code == 2
            assert device_3 == [32, 1]

    run(body)


def test_the_connection_closing_mid_chain_keeps_what_was_read() -> None:
    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        if index == 1:
            return 0.0, None, None  # hang up on device 2's request
        return 0.0, registers_pdu(body[0], [40 + index]), None

    chain = ((read_step(3, 0, 1, 1),), (read_step(3, 0, 1, 2),), (read_step(3, 0, 1, 3),))

    async def body() -> None:
        async with opened(ScriptedServer(script), timeout_s=TIMEOUT_S) as link:
            device_1, device_2, device_3 = await link.read_chain(chain)
            assert device_1 == [40]
            assert isinstance(device_2, ModbusLinkLostError)
            assert isinstance(device_3, ModbusLinkLostError)
            assert "connection lost" in str(device_3)
            assert not link.connected
            with pytest.raises(ModbusLinkLostError, match="connection lost"):
                await link.read_chain(chain)

    run(body)


def test_a_cancelled_chain_stops_and_the_next_waits_for_the_request_on_the_wire() -> None:
    """Cancelled while its request is unanswered: nothing more of it is sent, and the next
    chain's request goes out only once that reply is in (never two on the wire)."""

    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        return (0.5 if index == 0 else 0.0), registers_pdu(body[0], [50 + index]), None

    chain = ((read_step(3, 0, 1, 1),), (read_step(3, 0, 1, 2),))

    async def body() -> None:
        server = ScriptedServer(script)
        async with opened(server, timeout_s=TIMEOUT_S) as link:
            first = asyncio.ensure_future(link.read_chain(chain))
            await asyncio.sleep(0.1)
            first.cancel()
            assert await link.read_chain(chain[1:]) == [[51]]
            assert [unit_of(r) for r in server.requests] == [1, 2]
            assert server.most_outstanding == 1

    run(body)
