"""What the gateway needs from a CNC, independent of the protocol that carries it.

The compensation loop reads the spindle speed and run mode, and hands its value over
in a macro variable that it reads back to be sure the machine has it. Controllers
speak OPC UA or Modbus TCP (FOCAS cannot run here), so the loop talks to a
:class:`CncClient` and the drivers (``cnc_opcua``, ``cnc_modbus``) stay swappable.

:class:`ReconnectingSession` is the field-fault policy both drivers share: connect
lazily, drop the whole session on a link failure, reconnect after a :class:`Backoff`
with a brand-new library client (neither pymodbus nor asyncua rebuilds a session
reliably on its own: pymodbus #1635, asyncua #1660), and keep :class:`LinkHealth`.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

from drivers.backoff import Backoff
from drivers.link_health import LinkHealth

T = TypeVar("T")
SessionT = TypeVar("SessionT")


@dataclass(frozen=True)
class SpeedReading:
    """Spindle state at one read: actual and programmed speed (r/min), run mode.

    ``run_mode`` follows FANUC (0 STOP, 1 AUTO, 2 MDI, 3 JOG); None when the
    controller's map has no run mode.
    """

    actual_rpm: float
    commanded_rpm: float
    run_mode: int | None


@dataclass(frozen=True)
class GuardedWrite:
    """The outcome of :meth:`CncClient.write_macro_if`.

    ``held``: what the macro held just before the write (CNC unit; NaN: vacant);
    ``written``: False when that value failed the check and nothing was written.
    """

    held: float
    written: bool


@dataclass(frozen=True)
class MacroWrite:
    """One write of :meth:`CncClient.write_macros_if`: ``value`` to macro #``number`` only
    if ``holds`` what the macro holds right before."""

    number: int
    value: float
    holds: Callable[[float], bool]


class CncError(Exception):
    """A CNC call failed; the message names the endpoint and what failed."""


#: What :meth:`CncClient.read_macros` gives each macro: its value, or why it was not read.
MacroReads = dict[int, "float | CncError"]
#: What :meth:`CncClient.write_macros_if` gives each macro: its guarded write, or its error.
GuardedWrites = dict[int, "GuardedWrite | CncError"]


class CncRefusedError(CncError):
    """The CNC answered but refused the request (unknown node, illegal address, bad value).

    The link itself works, so the session is kept; retrying the same request will
    fail the same way until the configuration or the value changes.
    """


class CncClient(Protocol):
    """The gateway's view of a CNC. Every method raises :class:`CncError` on failure."""

    health: LinkHealth

    async def read_speed(self) -> SpeedReading: ...

    async def write_macro(self, number: int, value: float) -> None: ...

    async def read_macro(self, number: int) -> float: ...

    async def read_macros(self, numbers: Sequence[int]) -> MacroReads:
        """Macros #numbers in as few requests as the protocol allows (OPC UA: one Read;
        Modbus: one read per span of close registers), so a machine's axes cost one
        request, not one each. A macro the CNC refuses is a :class:`CncRefusedError` in
        its own entry and the others are read; a link failure raises :class:`CncError`."""
        ...

    async def write_macro_if(
        self, number: int, value: float, holds: Callable[[float], bool]
    ) -> GuardedWrite:
        """Read macro #number and write ``value`` only if ``holds(read)``: the read and
        the write go over one session with nothing awaited between them, so a value
        someone else put there is not overwritten unseen (only one landing between the
        read's reply and the write's arrival is)."""
        ...

    async def write_macros_if(self, writes: Sequence[MacroWrite]) -> GuardedWrites:
        """Each write as :meth:`write_macro_if` does it: its macro read, and written only if
        the read holds, with nothing awaited between that read's reply and that write's
        request. OPC UA: one Read of every macro, then one Write of those that hold;
        Modbus: each macro's read and write in turn (one write over several macros would
        also overwrite the registers between them). A macro the CNC refuses is its own
        :class:`CncRefusedError`; a link failure is every macro's :class:`CncError` not
        yet answered (OPC UA: raised)."""
        ...

    async def close(self) -> None: ...


class ReconnectingSession(Generic[SessionT]):
    """Runs CNC requests on a lazily opened session; reconnects with backoff after a loss.

    Subclasses say how to open and discard a session and which exceptions mean a
    broken link (``link_errors``). An operation that raises one of those drops the
    session and starts the backoff; :class:`CncRefusedError` keeps it (the peer answered).
    While the backoff runs, calls fail at once without I/O, so a dead CNC costs the
    gateway loop nothing. Constructors do no I/O.
    """

    #: Exceptions that mean the link or session is unusable (set by subclasses).
    link_errors: tuple[type[BaseException], ...] = (OSError, TimeoutError)

    def __init__(
        self,
        where: str,
        *,
        timeout_s: float,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.health = LinkHealth()
        self._where = where
        self._timeout_s = timeout_s
        self._backoff = backoff if backoff is not None else Backoff()
        self._clock = clock
        self._session: SessionT | None = None
        self._down_reason: str | None = None
        self._closed = False
        self._connect_lock = asyncio.Lock()

    async def _open(self) -> SessionT:
        """Connect and return a ready session (may raise any of ``link_errors``)."""
        raise NotImplementedError

    async def _discard(self, session: SessionT) -> None:
        """Release a session; must not raise (the link may already be dead)."""
        raise NotImplementedError

    @property
    def _connect_timeout_s(self) -> float:
        """Bound for a whole connect sequence (several round trips)."""
        return 3 * self._timeout_s

    async def _call(
        self, what: str, operation: Callable[[SessionT], Awaitable[T]], *args: object
    ) -> T:
        """Run ``operation(session, *args)`` on the session, connecting first if needed.

        ``what`` says what was attempted, for the error message. The operation
        runs in the caller's task; each of its requests is bounded by the library's
        own request timeout (pymodbus's ``timeout``, asyncua's client ``timeout``,
        both ``timeout_s``), the one timer on a request: a wrapping
        ``asyncio.wait_for`` would add a task and a timer to every request.
        """
        session = self._session
        if session is None or self._closed:
            session = await self._ensure_session(what)
        try:
            result = await operation(session, *args)
        except CncRefusedError as exc:
            self.health.record_ok(self._clock())  # the peer answered: the link is fine
            raise CncRefusedError(f"{self._where}: {what} refused: {exc}") from exc
        except self.link_errors as exc:
            message = f"{self._where}: {what} failed: {_describe(exc)}"
            await self._lose(message, session)
            raise CncError(message) from exc
        self.health.record_ok(self._clock())
        self._backoff.reset()
        return result

    async def _ensure_session(self, what: str) -> SessionT:
        # One connect at a time: concurrent callers must not each open a session.
        async with self._connect_lock:
            if self._closed:
                raise CncError(f"{self._where}: {what}: client is closed")
            if self._session is not None:
                return self._session
            now = self._clock()
            if not self._backoff.ready(now):
                reason = self._down_reason or "not connected"
                self.health.record_failure(reason)
                raise CncError(
                    f"{self._where}: {what}: not connected, next attempt in "
                    f"{self._backoff.wait_s(now):.2f} s (last error: {reason})"
                )
            try:
                async with asyncio.timeout(self._connect_timeout_s):
                    session = await self._open()
            except self.link_errors as exc:
                message = f"{self._where}: cannot connect ({_describe(exc)})"
                await self._lose(message, None)
                raise CncError(f"{message}; {what} not done") from exc
            if self._closed:  # close() ran while connecting
                await self._discard(session)
                raise CncError(f"{self._where}: {what}: client is closed")
            self._session = session
            self.health.record_connect()
            return session

    async def _lose(self, message: str, session: SessionT | None) -> None:
        """Record a link failure; drop ``session`` and start the backoff.

        ``session`` is the one the failed request used (None: a connect failed). When
        another caller has already dropped it, only the failure is recorded, so two
        requests failing together do not double the backoff.
        """
        self.health.record_failure(message)
        if session is not None:
            if self._session is not session:
                return
            self._session = None
            await self._discard(session)
        self._down_reason = message
        self._backoff.failed(self._clock())

    async def close(self) -> None:
        """Close the session; later calls raise :class:`CncError`. Idempotent."""
        self._closed = True
        session, self._session = self._session, None
        if session is not None:
            await self._discard(session)
        self.health.connected = False


def _describe(exc: BaseException) -> str:
    """Exception text for a message; a bare timeout says so instead of ''."""
    text = str(exc)
    if isinstance(exc, TimeoutError) and not text:
        return "timed out"
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
