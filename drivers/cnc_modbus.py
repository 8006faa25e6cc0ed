"""The CNC over Modbus TCP: spindle state in holding registers, macros as float32.

For controllers reached through an option board or a PLC gateway. The register
addresses are configurable; the defaults are the simulator's map (MODBUS.md):
float32 values in big-endian word order (high word at the lower address), the run
mode as uint16, macro #n at ``macro_base + 2·(n − macro_first)``, written with FC16.

The connection is :class:`drivers.transmitters.ModbusConnection` (the gateway's one
pymodbus client, with a life cycle the gateway owns); the reconnect policy is
:class:`drivers.cnc.ReconnectingSession`, shared with the OPC UA driver.
"""

from __future__ import annotations

import functools
import itertools
import math
import time
from collections.abc import Callable

from drivers.backoff import Backoff
from drivers.cnc import CncRefusedError, ReconnectingSession, SpeedReading
from drivers.register_codec import float32_to_registers, registers_to_float32_shortest
from drivers.transmitters import (
    ModbusConnection,
    ModbusLinkLostError,
    ModbusNoResponseError,
    ModbusRefusedError,
)

_FLOAT32_MAX = 3.4028234663852886e38
#: Register pairs → value, remembered: speeds and macros repeat from cycle to cycle, and
#: finding the shortest decimal takes up to nine formatting rounds.
_float32 = functools.lru_cache(maxsize=1024)(registers_to_float32_shortest)


class ModbusCnc(ReconnectingSession[ModbusConnection]):
    """A CNC reached over Modbus TCP; implements :class:`drivers.cnc.CncClient`.

    Connects on the first call. A request without an answer means the link is dead
    (the CNC is the only device behind the port), so it drops the connection and
    reconnects after the backoff; a Modbus exception reply is :class:`CncRefusedError`.
    """

    link_errors = (ModbusLinkLostError, ModbusNoResponseError, OSError, TimeoutError)

    def __init__(
        self,
        host: str,
        port: int,
        device_id: int = 1,
        speed_register: int = 0,
        commanded_register: int = 2,
        run_mode_register: int | None = 4,
        macro_base_register: int = 1000,
        macro_first: int = 500,
        timeout_s: float = 1.0,
        *,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 0 <= device_id <= 247:
            raise ValueError(f"device id {device_id} is outside the Modbus range 0–247")
        super().__init__(
            f"Modbus TCP {host}:{port} device {device_id}",
            timeout_s=timeout_s,
            backoff=backoff,
            clock=clock,
        )
        self.host = host
        self.port = port
        self.device_id = device_id
        self._speed_register = speed_register
        self._commanded_register = commanded_register
        self._run_mode_register = run_mode_register
        self._macro_base = macro_base_register
        self._macro_first = macro_first
        #: (start register, count) of each value read by read_speed.
        self._items = [(speed_register, 2), (commanded_register, 2)]
        if run_mode_register is not None:
            self._items.append((run_mode_register, 1))
        self._span = _contiguous_span(self._items)
        self._macro_requests: dict[tuple[int, str], tuple[int, str]] = {}

    def macro_register(self, number: int) -> int:
        """First (high-word) register of macro #number."""
        if number < self._macro_first:
            raise ValueError(f"macro #{number} is below the mapped range from #{self._macro_first}")
        register = self._macro_base + 2 * (number - self._macro_first)
        if register + 1 > 0xFFFF:
            raise ValueError(f"macro #{number} maps beyond register 65535")
        return register

    # -- CncClient ----------------------------------------------------------------

    async def read_speed(self) -> SpeedReading:
        """Actual and commanded speed and run mode; one request when they are adjacent."""
        return await self._call("reading spindle speed", self._read_speed)

    async def write_macro(self, number: int, value: float) -> None:
        """FC16 write of macro #number as float32.

        Non-finite values and values beyond float32 raise ``ValueError`` before any
        I/O: a NaN or a saturated value must never reach a machine offset.
        """
        register, what = self._macro_request(number, "writing")
        if not math.isfinite(value) or abs(value) > _FLOAT32_MAX:
            raise ValueError(f"macro #{number}: {value!r} is not a finite float32")
        await self._call(what, self._write_words, register, list(float32_to_registers(value)))

    async def read_macro(self, number: int) -> float:
        """Read macro #number back (NaN for a vacant variable, as the CNC reports it)."""
        register, what = self._macro_request(number, "reading")
        return await self._call(what, self._read_float32, register)

    def _macro_request(self, number: int, verb: str) -> tuple[int, str]:
        """Register of macro #number and the words for an error message (built once)."""
        key = (number, verb)
        request = self._macro_requests.get(key)
        if request is None:
            register = self.macro_register(number)
            request = (register, f"{verb} macro #{number} (register {register})")
            self._macro_requests[key] = request
        return request

    # -- requests (run by ReconnectingSession._call on the open connection) ----------

    async def _read_speed(self, link: ModbusConnection) -> SpeedReading:
        words = await self._read_items(link)
        run_mode = None
        if self._run_mode_register is not None:
            run_mode = words[self._run_mode_register][0]
        return SpeedReading(
            actual_rpm=_float32(*words[self._speed_register]),
            commanded_rpm=_float32(*words[self._commanded_register]),
            run_mode=run_mode,
        )

    async def _write_words(self, link: ModbusConnection, register: int, words: list[int]) -> None:
        try:
            await link.write_registers(register, words, self.device_id)
        except ModbusRefusedError as exc:
            raise CncRefusedError(str(exc)) from exc

    async def _read_float32(self, link: ModbusConnection, register: int) -> float:
        high, low = await self._read_holding(link, register, 2)
        return _float32(high, low)

    async def _read_holding(self, link: ModbusConnection, register: int, count: int) -> list[int]:
        """Holding registers; an exception reply becomes :class:`CncRefusedError`."""
        try:
            return await link.read_holding_registers(register, count, self.device_id)
        except ModbusRefusedError as exc:
            raise CncRefusedError(str(exc)) from exc

    # -- session life cycle ---------------------------------------------------------

    async def _open(self) -> ModbusConnection:
        link = ModbusConnection(tcp=(self.host, self.port), timeout_s=self._timeout_s, retries=0)
        await link.open()
        return link

    async def _discard(self, session: ModbusConnection) -> None:
        session.close()

    async def _read_items(self, link: ModbusConnection) -> dict[int, list[int]]:
        """The registers of speed, commanded speed and run mode, by start address."""
        if self._span is not None:
            start, count = self._span
            registers = await self._read_holding(link, start, count)
            return {a: registers[a - start : a - start + n] for a, n in self._items}
        return {a: await self._read_holding(link, a, n) for a, n in self._items}


def _contiguous_span(blocks: list[tuple[int, int]]) -> tuple[int, int] | None:
    """(start, count) when the register blocks tile one range without gaps, else None.

    Reading them in one request gives values from the same instant; a gap could be
    unmapped on the CNC (an exception for the whole request), so then each is read
    on its own.
    """
    ordered = sorted(blocks)
    for (start, count), (next_start, _) in itertools.pairwise(ordered):
        if start + count != next_start:
            return None
    first, last = ordered[0], ordered[-1]
    return first[0], last[0] + last[1] - first[0]
