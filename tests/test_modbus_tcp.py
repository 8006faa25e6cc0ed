"""The lean Modbus TCP client (drivers.modbus_tcp) against a scripted server on loopback.

The scripted server is a real TCP server that answers each request as the test
tells it: late, with an exception, with another device id, or by hanging up. It
checks what pymodbus's servers cannot provoke on demand: a late reply to a
timed-out request is never taken for the next request's reply.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Callable

import pytest

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
                delay_s, pdu, device_id = self._script(index, body)
                if pdu is None:
                    writer.close()
                    return
                asyncio.get_running_loop().call_later(
                    delay_s, self._reply, writer, header, pdu, device_id
                )
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.close()

    @staticmethod
    def _reply(
        writer: asyncio.StreamWriter, header: bytes, pdu: bytes, device_id: int | None
    ) -> None:
        if writer.is_closing():
            return
        unit = header[6] if device_id is None else device_id
        writer.write(header[0:4] + (len(pdu) + 1).to_bytes(2, "big") + bytes((unit,)) + pdu)


def run(body: Callable[[], object]) -> None:
    asyncio.run(asyncio.wait_for(body(), 60))  # type: ignore[arg-type]


def test_a_late_reply_is_never_taken_for_the_next_request() -> None:
    """Request 0 is answered after its timeout; request 1 must get its own registers."""

    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        delay_s = TIMEOUT_S + 0.5 if index == 0 else 0.0
        return delay_s, registers_pdu(body[0], [100 + index, 7]), None

    async def body() -> None:
        async with ScriptedServer(script) as address:
            link = ModbusConnection(tcp=address, timeout_s=TIMEOUT_S)
            await link.open()
            try:
                with pytest.raises(ModbusNoResponseError, match="no response from device 3"):
                    await link.read_input_registers(0, 2, device_id=3)
                assert await link.read_holding_registers(0, 2, device_id=3) == [101, 7]
                await asyncio.sleep(0.7)  # the late reply to request 0 arrives meanwhile
                assert await link.read_holding_registers(0, 2, device_id=3) == [102, 7]
                assert link.connected
            finally:
                link.close()

    run(body)


def test_retries_send_the_request_again() -> None:
    def script(index: int, body: bytes) -> tuple[float, bytes | None, int | None]:
        delay_s = 10.0 if index == 0 else 0.0  # the first attempt is never answered in time
        return delay_s, registers_pdu(body[0], [index]), None

    async def body() -> None:
        server = ScriptedServer(script)
        async with server as address:
            link = ModbusConnection(tcp=address, timeout_s=1.0, retries=1)
            await link.open()
            try:
                assert await link.read_holding_registers(5, 1, device_id=1) == [1]
                assert len(server.requests) == 2
                tids = {request[0:2] for request in server.requests}
                assert len(tids) == 2  # a fresh transaction id for the second attempt
            finally:
                link.close()

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
        async with ScriptedServer(script) as address:
            link = ModbusConnection(tcp=address, timeout_s=1.0)
            await link.open()
            try:
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
            finally:
                link.close()

    run(body)
