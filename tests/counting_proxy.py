"""A loopback TCP proxy that counts the requests a client sends to a CNC, by kind.

It forwards bytes both ways unchanged and parses the client's stream into frames:
Modbus TCP (MBAP header: the length at bytes 4–5; the kind is the function code) or
OPC UA over an unsecured channel (message header: type, chunk and size; the kind of a
``MSG`` is its service request: ``read``, ``write`` or the request type's numeric id).
So a test counts what really went on the wire, whatever the client library does.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
from collections import Counter

#: OPC UA binary encoding ids of the service requests a test tells apart.
OPCUA_SERVICES = {631: "read", 673: "write"}
MODBUS_FUNCTIONS = {3: "read", 16: "write"}


class CountingProxy:
    """Listens on a free loopback port and forwards each connection to ``upstream``."""

    def __init__(self, upstream: tuple[str, int], protocol: str) -> None:
        if protocol not in ("modbus", "opcua"):
            raise ValueError(f"protocol {protocol!r}: expected modbus or opcua")
        self.upstream = upstream
        self.protocol = protocol
        self.counts: Counter[str] = Counter()
        self._server: asyncio.Server | None = None
        self._pipes: set[asyncio.Task[None]] = set()

    @property
    def port(self) -> int:
        assert self._server is not None
        return int(self._server.sockets[0].getsockname()[1])

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
        for task in list(self._pipes):
            task.cancel()
        for task in list(self._pipes):
            with contextlib.suppress(asyncio.CancelledError, OSError):
                await task

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(*self.upstream)
        for pipe in (self._requests(reader, up_writer), self._copy(up_reader, writer)):
            task = asyncio.ensure_future(pipe)
            self._pipes.add(task)
            task.add_done_callback(self._pipes.discard)

    async def _copy(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        finally:
            writer.close()

    async def _requests(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Forward the client's frames one by one, counting each."""
        head = 6 if self.protocol == "modbus" else 8
        try:
            while True:
                try:
                    header = await reader.readexactly(head)
                except asyncio.IncompleteReadError:
                    return
                if self.protocol == "modbus":
                    body = await reader.readexactly(struct.unpack(">H", header[4:6])[0])
                    self.counts[MODBUS_FUNCTIONS.get(body[1], f"fc{body[1]}")] += 1
                else:
                    body = await reader.readexactly(struct.unpack("<I", header[4:8])[0] - 8)
                    self.counts[self._opcua_kind(header, body)] += 1
                writer.write(header + body)
                await writer.drain()
        finally:
            writer.close()

    @staticmethod
    def _opcua_kind(header: bytes, body: bytes) -> str:
        """``MSG`` final chunks by service (channel id, token id, sequence number and
        request id come before the request's four-byte encoded type id); other
        messages (HEL, OPN, CLO) by their type."""
        kind = header[:3].decode("ascii")
        if kind != "MSG" or header[3:4] != b"F" or body[16] != 0x01:
            return kind
        type_id = struct.unpack("<H", body[18:20])[0]
        return OPCUA_SERVICES.get(type_id, str(type_id))
