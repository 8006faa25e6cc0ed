"""The CNC over Modbus TCP: spindle state in holding registers, macros as float32.

For controllers reached through an option board or a PLC gateway. The registers
are a :class:`drivers.schema.RegisterMap` (fields ``actual_speed_rpm``,
``commanded_speed_rpm``, optional ``run_mode``, and a ``macros`` block), in any
byte and word order; without one, the ``*_register`` addresses describe the
simulator's layout (``drivers/maps/sim_cnc.yaml``, MODBUS.md): float32 with the
high word at the lower address, the run mode as uint16, macro #n at
``macro_base + 2·(n − macro_first)``, written with FC16. The spindle state is
read in one request per contiguous block, sent as one chain (each request
written from the previous one's reply, :mod:`drivers.modbus_tcp`); a map's
``pause_between_requests_s`` is kept instead, before every request to the CNC,
counted from the end of the previous one (:class:`drivers.bus_hub.Silence`, the
transmitter hub's inter-frame silence).

The connection is :class:`drivers.transmitters.ModbusConnection` (the gateway's one
pymodbus client, with a life cycle the gateway owns); the reconnect policy is
:class:`drivers.cnc.ReconnectingSession`, shared with the OPC UA driver.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import TypeVar

from drivers.backoff import Backoff
from drivers.bus_hub import Silence
from drivers.cnc import (
    CncError,
    CncRefusedError,
    GuardedWrite,
    GuardedWrites,
    MacroReads,
    MacroWrite,
    ReconnectingSession,
    SpeedReading,
)
from drivers.modbus_tcp import Step, read_step
from drivers.register_map import DeviceRegisters, MacroLayout
from drivers.schema import RegisterMap, Workarounds, check_cnc_map, cnc_map
from drivers.transmitters import (
    ModbusConnection,
    ModbusLinkLostError,
    ModbusNoResponseError,
    ModbusRefusedError,
    ModbusRequestError,
    read_steps,
)

T = TypeVar("T")

_FLOAT32_MAX = 3.4028234663852886e38
#: The most registers one read of several macros covers (macros farther apart: more reads).
MACRO_SPAN_REGISTERS = 32


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
        register_map: RegisterMap | None = None,
        workarounds: Workarounds | None = None,
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
        if register_map is None:
            register_map = cnc_map(
                speed_register,
                commanded_register,
                run_mode_register,
                macro_base_register,
                macro_first,
            )
        check_cnc_map(register_map)
        self.registers = DeviceRegisters(register_map, workarounds)
        assert self.registers.macros is not None  # check_cnc_map made sure
        self._macros: MacroLayout = self.registers.macros
        self._has_run_mode = "run_mode" in self.registers.fields
        self._pause_s = self.registers.workarounds.pause_between_requests_s
        self._silence = Silence()
        #: The spindle state's read requests as one chain group (built once).
        self._speed_chain = (read_steps(self.registers.requests, device_id),)

    def macro_register(self, number: int) -> int:
        """First register of macro #number."""
        return self._macros.register(number)

    # -- CncClient ----------------------------------------------------------------

    async def read_speed(self) -> SpeedReading:
        """Actual and commanded speed and run mode; one request when they are adjacent."""

        async def read(link: ModbusConnection) -> SpeedReading:
            values = self.registers.decode(await self._read_requests(link))
            return SpeedReading(
                actual_rpm=values["actual_speed_rpm"],
                commanded_rpm=values["commanded_speed_rpm"],
                run_mode=int(values["run_mode"]) if self._has_run_mode else None,
            )

        return await self._call("reading spindle speed", read)

    async def write_macro(self, number: int, value: float) -> None:
        """FC16 write of macro #number as float32.

        Non-finite values and values beyond float32 raise ``ValueError`` before any
        I/O: a NaN or a saturated value must never reach a machine offset.
        """
        register, words = self._encoded(number, value)

        async def write(link: ModbusConnection) -> None:
            await self._paced(lambda: link.write_registers(register, words, self.device_id))

        await self._call(f"writing macro #{number} (register {register})", write)

    async def write_macro_if(
        self, number: int, value: float, holds: Callable[[float], bool]
    ) -> GuardedWrite:
        """FC3 read of macro #number, then, only if ``holds(read)``, its FC16 write on
        the same connection; nothing else is awaited between the read's reply and the
        write request (Modbus has no conditional write: that gap is what remains)."""
        register, words = self._encoded(number, value)

        async def read_then_write(link: ModbusConnection) -> GuardedWrite:
            held = await self._read_macro(link, register)
            if not holds(held):
                return GuardedWrite(held, written=False)
            await self._paced(lambda: link.write_registers(register, words, self.device_id))
            return GuardedWrite(held, written=True)

        return await self._call(
            f"checking and writing macro #{number} (register {register})", read_then_write
        )

    async def write_macros_if(self, writes: Sequence[MacroWrite]) -> GuardedWrites:
        """Each macro's FC3 read and, if it holds, its FC16 write (:meth:`write_macro_if`), in
        turn: a macro's failure is its own entry, and a write that landed is never reported
        lost because a later macro's link failed."""
        for write in writes:
            self._encoded(write.number, write.value)  # ValueError before any I/O
        results: GuardedWrites = {}
        for write in writes:
            try:
                results[write.number] = await self.write_macro_if(
                    write.number, write.value, write.holds
                )
            except CncError as exc:
                results[write.number] = exc
        return results

    def _encoded(self, number: int, value: float) -> tuple[int, list[int]]:
        """First register and float32 words of macro #number = ``value``; a non-finite
        value or one beyond float32 raises ``ValueError`` before any I/O."""
        register = self.macro_register(number)
        if not math.isfinite(value) or abs(value) > _FLOAT32_MAX:
            raise ValueError(f"macro #{number}: {value!r} is not a finite float32")
        return register, self._macros.encode(value)

    async def read_macro(self, number: int) -> float:
        """Read macro #number back (NaN for a vacant variable, as the CNC reports it)."""
        register = self.macro_register(number)

        return await self._call(
            f"reading macro #{number} (register {register})",
            functools.partial(self._read_macro, register=register),
        )

    async def read_macros(self, numbers: Sequence[int]) -> MacroReads:
        """Macros #numbers, one FC3 read per span of at most ``MACRO_SPAN_REGISTERS``
        registers (the registers between them read and dropped). A span the CNC refuses
        (an unmapped register inside it) is read again macro by macro, so only the
        macro it refuses is that macro's :class:`CncRefusedError`."""
        registers = {number: self.macro_register(number) for number in dict.fromkeys(numbers)}
        spans = _spans(sorted(registers.values()), self._macros.width)

        async def read(link: ModbusConnection) -> MacroReads:
            results: MacroReads = {}
            for start, count in spans:
                inside = [n for n, r in registers.items() if start <= r < start + count]
                try:
                    words = await self._read_span(link, start, count)
                except CncRefusedError as exc:
                    if len(inside) == 1:
                        results[inside[0]] = self._refused(inside[0], exc)
                        continue
                    for number in inside:  # which one is refused: each on its own
                        try:
                            results[number] = await self._read_macro(link, registers[number])
                        except CncRefusedError as one:
                            results[number] = self._refused(number, one)
                    continue
                for number in inside:
                    offset = registers[number] - start
                    results[number] = self._macros.decode(
                        words[offset : offset + self._macros.width]
                    )
            return results

        listed = ", ".join(f"#{number}" for number in registers)
        return await self._call(f"reading macros {listed}", read)

    def _refused(self, number: int, exc: CncRefusedError) -> CncError:
        register = self.macro_register(number)
        return CncRefusedError(
            f"{self._where}: reading macro #{number} (register {register}) refused: {exc}"
        )

    async def _read_span(self, link: ModbusConnection, start: int, count: int) -> list[int]:
        if self._chains_on(link):  # read_step builds each shape once
            return await self._chained(link, ((read_step(3, start, count, self.device_id),),))
        return await self._paced(lambda: link.read_holding_registers(start, count, self.device_id))

    async def _read_macro(self, link: ModbusConnection, register: int) -> float:
        width = self._macros.width
        if self._chains_on(link):  # read_step builds each shape once
            chain = ((read_step(3, register, width, self.device_id),),)
            return self._macros.decode(await self._chained(link, chain))
        words = await self._paced(
            lambda: link.read_holding_registers(register, width, self.device_id)
        )
        return self._macros.decode(words)

    # -- session life cycle ---------------------------------------------------------

    async def _open(self) -> ModbusConnection:
        link = ModbusConnection(tcp=(self.host, self.port), timeout_s=self._timeout_s, retries=0)
        await link.open()
        self._silence.reset()
        return link

    async def _discard(self, session: ModbusConnection) -> None:
        session.close()

    async def _read_requests(self, link: ModbusConnection) -> list[int]:
        """The map's read requests in turn (one per contiguous block), replies concatenated:
        one chain on the wire when no pause is kept between them (TCP always chains)."""
        if self._chains_on(link):
            return await self._chained(link, self._speed_chain)
        registers: list[int] = []
        for request in self.registers.requests:
            registers += await self._paced(functools.partial(link.read, request, self.device_id))
        return registers

    def _chains_on(self, link: ModbusConnection) -> bool:
        """Requests go as chains: the link runs them (TCP) and the map keeps no pause."""
        return self._pause_s == 0 and link.chains

    async def _chained(self, link: ModbusConnection, chain: tuple[tuple[Step, ...]]) -> list[int]:
        """One device read (a group of register reads) as a chain on the wire; an exception
        reply is :class:`CncRefusedError`."""
        (result,) = await link.read_chain(chain)
        if isinstance(result, ModbusRefusedError):
            raise CncRefusedError(str(result)) from result
        if isinstance(result, ModbusRequestError):
            raise result
        return result

    async def _paced(self, send: Callable[[], Awaitable[T]]) -> T:
        """One request after the map's pause; an exception reply is :class:`CncRefusedError`."""
        try:
            if self._pause_s > 0:
                return await self._silence.around(send, self._pause_s)
            return await send()
        except ModbusRefusedError as exc:
            raise CncRefusedError(str(exc)) from exc


def _spans(registers: Sequence[int], width: int) -> list[tuple[int, int]]:
    """(first register, count) of the reads covering macros that start at ``registers``
    (sorted): consecutive macros share a read while it spans at most
    ``MACRO_SPAN_REGISTERS``."""
    spans: list[tuple[int, int]] = []
    for register in registers:
        if spans and register + width - spans[-1][0] <= max(MACRO_SPAN_REGISTERS, width):
            start = spans[-1][0]
            spans[-1] = (start, register + width - start)
        else:
            spans.append((register, width))
    return spans
