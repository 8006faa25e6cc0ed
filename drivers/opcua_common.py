"""What this project's OPC UA servers share: engineering units and the server life cycle.

Used by the simulated CNC (``simulator.servers.opcua_cnc``) and the gateway's SCADA
server (``gateway.scada.server``), so both encode units the same way and start, fail
and stop the same way.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from types import TracebackType
from typing import Any, Self, cast

from asyncua import Server, ua

# asyncua types a node id's parts, a status code and a timestamp as its own subclasses of
# int, str and datetime, and a DataValue's value as a Variant, where its constructors take
# the plain values too; these helpers say so once, with the values the wire carries.


def node_id(identifier: int | str, namespace: int = 0) -> ua.NodeId:
    """A numeric or string node id in ``namespace``."""
    ident = ua.Int32(identifier) if isinstance(identifier, int) else ua.String(identifier)
    return ua.NodeId(ident, ua.Int16(namespace))


def ua_datetime(value: datetime) -> ua.DateTime:
    """A timestamp as asyncua types it (its DateTime adds nothing to a datetime)."""
    return cast(ua.DateTime, value)


def status_code(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))


def data_value(value: Any, status: int = ua.StatusCodes.Good, stamped: bool = True) -> ua.DataValue:
    """``value`` (a Variant, or what a Variant holds) with a status and, when
    ``stamped``, the source and server time of now."""
    variant = value if isinstance(value, ua.Variant) else ua.Variant(value)
    now = ua_datetime(datetime.now(UTC)) if stamped else None
    return ua.DataValue(
        variant, StatusCode=status_code(status), SourceTimestamp=now, ServerTimestamp=now
    )


# UNECE Recommendation 20 unit codes, encoded as OPC UA EUInformation.UnitId
# (OPC UA Part 8, 5.6.3: the code's ASCII bytes packed into an Int32).
UNECE_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"


def unece_unit_id(code: str) -> int:
    unit_id = 0
    for char in code:
        unit_id = (unit_id << 8) | ord(char)
    return unit_id


def engineering_units(code: str, symbol: str, description: str) -> ua.EUInformation:
    return ua.EUInformation(
        NamespaceUri=UNECE_NAMESPACE,
        UnitId=unece_unit_id(code),
        DisplayName=ua.LocalizedText(symbol),
        Description=ua.LocalizedText(description),
    )


CELSIUS = engineering_units("CEL", "°C", "degree Celsius")
RPM = engineering_units("RPM", "r/min", "revolutions per minute")
SECOND = engineering_units("SEC", "s", "second")
MICROMETRE = engineering_units("4H", "µm", "micrometre")


class ServerLifecycle:
    """Start once, roll back a failed start, stop idempotently, ``async with``.

    Subclasses configure an asyncua ``Server`` in their own ``start`` and hand it
    to :meth:`_listen` with the code that fills its address space.
    """

    _server: Server | None = None

    def _refuse_second_start(self) -> None:
        if self._server is not None:
            raise RuntimeError("server already started")

    async def _listen(self, server: Server, prepare: Callable[[Server], Awaitable[None]]) -> None:
        """Keep ``server``, run ``prepare`` (address space, first values), then listen.

        If anything fails the server is stopped and forgotten, so nothing is left
        half-started and ``start`` may be tried again.
        """
        self._server = server
        try:
            await prepare(server)
            await server.start()
        except BaseException:
            self._server = None
            await server.stop()
            raise

    async def stop(self) -> None:
        """Close client connections and the listening socket (idempotent)."""
        server, self._server = self._server, None
        if server is not None:
            await _end_time_task(server)
            await server.stop()

    def _require_started(self) -> Server:
        if self._server is None:
            raise RuntimeError("server not started")
        return self._server

    async def start(self) -> None:
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()


async def _end_time_task(server: Server) -> None:
    """Cancel the server's once-a-second clock update instead of waiting for it.

    asyncua's ``InternalServer.stop`` flags that task and awaits it, which waits
    out its ``sleep(1)``: every stop took a second, and a gateway must stop within
    one (SIGTERM). Cancelled here, ``stop`` finds no task left to wait for.
    """
    internal = server.iserver
    task = getattr(internal, "time_task", None)
    if task is None:
        return
    task.cancel()
    await asyncio.wait({task})  # its end, without raising its CancelledError here
    internal.time_task = None
