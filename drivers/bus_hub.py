"""One hub per physical bus: the serial port, its lock, its silences and its reconnects.

Two machines whose transmitters hang on one RS-485 line must not open the port
twice: two masters on one line collide, and each would read the other's replies.
As in Home Assistant's modbus hub, the line is one :class:`BusHub`, found by its
port path in a :class:`BusHubs` registry, that every user of the line shares:

* one port, opened once and closed when its last user detaches;
* one lock: a user's read of its devices is one transaction sequence under it,
  so frames of two machines never interleave. ``asyncio.Lock`` serves waiters in
  arrival order, so a machine whose device is silent delays the other by its
  bounded timeout, never starves it;
* the inter-frame silence: Modbus RTU wants 3.5 character times between frames
  (1.75 ms above 19200 baud, where the specification fixes it), or a configured
  minimum for a slow device, or the pause a device's register map asks for
  between requests, whichever is longest; pymodbus's async serial client does
  not wait it, so the hub does before every request (:class:`Silence`, which the
  CNC's Modbus driver uses for its map's pause too);
* one reconnect back-off (:class:`drivers.backoff.Backoff`): a lost port is
  reopened once for everybody. Silence alone closes it only when every user of
  the line found no device answering since the last answer, so one machine's
  dead module never takes the port from another machine's live ones.

The hub knows nothing of transmitters; :class:`drivers.transmitters.TransmitterBus`
is its user. Times for the back-off are the caller's ``now_s``; the inter-frame
silence is physical, so it is measured on the event loop's monotonic clock.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol, TypeVar

from drivers.backoff import Backoff

T = TypeVar("T")

#: Character of an RTU frame: start bit, 8 data bits, parity or second stop bit, stop bit.
BITS_PER_CHARACTER = 11
#: Above this rate the RTU silence is fixed instead of scaling with the character time.
FIXED_SILENCE_ABOVE_BAUD = 19200
FIXED_SILENCE_S = 0.00175


def rtu_silence_s(baudrate: int) -> float:
    """The Modbus RTU inter-frame silence t3.5 at ``baudrate`` (serial line spec, 2.5.1.1)."""
    if baudrate <= 0:
        raise ValueError(f"baudrate must be > 0, got {baudrate}")
    if baudrate > FIXED_SILENCE_ABOVE_BAUD:
        return FIXED_SILENCE_S
    return 3.5 * BITS_PER_CHARACTER / baudrate


class Silence:
    """The quiet time a line or device needs before the next request.

    Counted from the end of the previous request (its reply or its timeout), on the
    system's monotonic clock: the silence is physical, not machine time. Not the event
    loop's clock: uvloop's is read once per loop iteration and its timers round to whole
    milliseconds, so a 1.75 ms t3.5 could end after 1 ms. The wait sleeps again until
    the clock says the whole silence has passed.
    """

    def __init__(self) -> None:
        self._quiet_since: float | None = None

    def reset(self) -> None:
        """A fresh connection: nothing to wait for."""
        self._quiet_since = None

    async def around(self, send: Callable[[], Awaitable[T]], silence_s: float) -> T:
        """Wait until the line was quiet for ``silence_s``, then run ``send()``."""
        if silence_s > 0 and self._quiet_since is not None:
            quiet_until = self._quiet_since + silence_s
            while (wait_s := quiet_until - time.monotonic()) > 0:
                await asyncio.sleep(wait_s)
        try:
            return await send()
        finally:
            self._quiet_since = time.monotonic()


class Link(Protocol):
    """What a hub needs of its connection (``drivers.transmitters.ModbusConnection`` has it)."""

    @property
    def where(self) -> str: ...

    @property
    def connected(self) -> bool: ...

    async def open(self) -> None: ...

    def close(self) -> None: ...


@dataclass
class Session:
    """One user's turn on the bus, handed out by :meth:`BusHub.transaction`.

    ``failure`` is why the port is not usable now (the user reports its devices as
    failed with it); ``reopened`` is True when the port was (re)opened since this
    user's previous turn. The user tells how its turn went with :meth:`report`.
    """

    failure: str | None
    reopened: bool
    answered: bool = False
    lost: str | None = None

    def report(self, *, answered: bool, lost: str | None) -> None:
        """``answered``: some device replied; ``lost``: the link broke (why)."""
        self.answered = answered
        self.lost = lost


class BusHub:
    """One physical bus (an RS-485 port, or one TCP connection) shared by its users.

    ``link`` is the connection (the hub opens and closes it), ``silence_s`` the
    pause between the end of one frame exchange and the next request. The
    constructor does no I/O.
    """

    def __init__(self, link: Link, *, silence_s: float = 0.0, backoff: Backoff | None = None):
        if not silence_s >= 0:
            raise ValueError(f"silence_s must be >= 0, got {silence_s}")
        self.link = link
        self.silence_s = silence_s
        self.backoff = backoff if backoff is not None else Backoff()
        #: Ports opened so far; a user that saw another number was reconnected meanwhile.
        self.opens = 0
        #: Requests sent and transactions served, over the hub's life.
        self.requests = 0
        self.transactions = 0
        self._lock = asyncio.Lock()
        self._users: set[object] = set()
        self._silent_users: set[object] = set()
        self._seen_opens: dict[object, int] = {}
        self._down_reason: str | None = None
        self._silence = Silence()

    @property
    def where(self) -> str:
        return self.link.where

    @property
    def users(self) -> int:
        return len(self._users)

    def attach(self, user: object) -> None:
        """``user`` reads on this bus from now on (idempotent)."""
        self._users.add(user)

    def detach(self, user: object) -> None:
        """``user`` is done; the port closes with the last user (idempotent)."""
        self._users.discard(user)
        self._silent_users.discard(user)
        if not self._users:
            self.link.close()
            self._silence.reset()

    def transaction(self, user: object, now_s: float) -> _Transaction:
        """Hold the bus for ``user``'s requests: lock, open the port if the back-off
        allows, then hand out a :class:`Session`; the report decides on reconnects.

        ``async with hub.transaction(user, now_s) as session:`` (a plain context
        manager object rather than an async generator: one per bus and cycle).
        """
        return _Transaction(self, user, now_s)

    async def _begin(self, user: object, now_s: float) -> Session:
        """Lock the bus and hand out ``user``'s session (the lock is released on a raise)."""
        self.attach(user)
        await self._lock.acquire()
        try:
            failure = await self._ensure_open(now_s)
        except BaseException:
            self._lock.release()
            raise
        reopened = self._seen_opens.get(user) != self.opens  # a first turn counts too
        self._seen_opens[user] = self.opens
        self.transactions += 1
        return Session(failure=failure, reopened=reopened and failure is None)

    def _end(self, user: object, session: Session, now_s: float, cut_short: bool) -> None:
        """After the turn: settle the port (or close it if cut short), then unlock."""
        try:
            if cut_short:
                # Cut short (a stop, a cancelled cycle): a reply may still be on its way,
                # so the next user starts on a freshly opened port instead.
                self.link.close()
            elif session.failure is None:
                self._settle(user, session, now_s)
        finally:
            self._lock.release()

    async def request(self, send: Callable[[], Awaitable[T]], *, pause_s: float = 0.0) -> T:
        """Send one request (inside a transaction) once the bus has been silent long enough:
        the hub's silence, or ``pause_s`` (the device's own need) if that is longer."""
        self.requests += 1
        return await self._silence.around(send, max(self.silence_s, pause_s))

    async def _ensure_open(self, now_s: float) -> str | None:
        """None when the port is open (opening it if the back-off allows), else why not."""
        if self.link.connected:
            return None
        if not self.backoff.ready(now_s):
            reason = self._down_reason or f"{self.where}: not connected"
            return f"{reason} (next connection attempt in {self.backoff.wait_s(now_s):.2f} s)"
        try:
            await self.link.open()
        except Exception as exc:  # the link's own error type, with its message
            self._down_reason = str(exc)
            self.backoff.failed(now_s)
            return str(exc)
        self.opens += 1
        self._silent_users.clear()
        self._silence.reset()
        return None

    def _settle(self, user: object, session: Session, now_s: float) -> None:
        """After a turn: an answer keeps the port; a broken link, or silence from every
        user's devices since the last answer, closes it for one reconnect."""
        if session.answered:
            self.backoff.reset()
            self._silent_users.clear()
        elif session.lost is None:
            self._silent_users.add(user)
        if session.lost is not None:
            reason = session.lost
        elif self._users and self._silent_users >= self._users:
            reason = f"{self.where}: no device answered"
        else:
            return
        self.link.close()
        self._down_reason = reason
        self._silent_users.clear()
        self.backoff.failed(now_s)


class _Transaction:
    """``BusHub.transaction``'s context manager: the turn starts on entry, settles on exit."""

    __slots__ = ("_hub", "_now_s", "_session", "_user")

    def __init__(self, hub: BusHub, user: object, now_s: float) -> None:
        self._hub = hub
        self._user = user
        self._now_s = now_s
        self._session: Session | None = None

    async def __aenter__(self) -> Session:
        self._session = await self._hub._begin(self._user, self._now_s)
        return self._session

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        assert self._session is not None
        self._hub._end(self._user, self._session, self._now_s, cut_short=exc_type is not None)


class HubSettingsError(ValueError):
    """Two users of one port asked for different line settings (baud rate, parity)."""


class BusHubs:
    """The hubs of one gateway, one per port: ``("rtu", path)`` or ``("tcp", host, port)``.

    The first user of a port creates its hub with its line settings; a later user
    must ask for the same settings (two baud rates on one line cannot both be
    right). The configuration refuses such a mismatch before anything runs; this
    is the backstop for callers that build buses by hand.
    """

    def __init__(self) -> None:
        self._hubs: dict[tuple[object, ...], tuple[object, BusHub]] = {}

    def __len__(self) -> int:
        return len(self._hubs)

    def get(self, key: tuple[object, ...], settings: object, make: Callable[[], BusHub]) -> BusHub:
        """The hub of ``key``, made by ``make()`` for its first user."""
        known = self._hubs.get(key)
        if known is None:
            hub = make()
            self._hubs[key] = (settings, hub)
            return hub
        known_settings, hub = known
        if known_settings != settings:
            raise HubSettingsError(
                f"{hub.where} is already open with {known_settings}, asked for {settings}"
            )
        return hub
