"""Temperature transmitters over Modbus RTU or TCP, and the gateway's one pymodbus client.

Pt100 input modules (8 channels each, one device id per module, several per RS-485
bus or behind one TCP port) report 0.1 °C counts and a status per channel; each
device's registers are a :class:`drivers.schema.RegisterMap` (by default
``drivers/maps/pt100_8ch.yaml``, documented in ``simulator/servers/MODBUS.md``).
:class:`TransmitterBus` reads every module once per cycle and never raises for a
field fault: each channel comes back with a value or with the reason it has none.

:class:`ModbusConnection` is the only place in the gateway that talks Modbus (the
CNC Modbus driver builds on it too), so the next pymodbus API change is fixed once.
Over TCP it drives pymodbus's framer and PDUs on a lean protocol of its own
(:mod:`drivers.modbus_tcp`: the library's transaction layer costs more CPU per
request than the socket does); over RTU it uses pymodbus's serial client. It owns
the client's life cycle instead of relying on pymodbus's: the library does not
reconnect after a cable re-plug (#1635), busy-loops with ``reconnect_delay=0``
(#1794) and closes the whole port after a few silent requests, taking every other
slave on the bus down with one dead one (#1654).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import struct
from collections.abc import Awaitable, Sequence
from dataclasses import dataclass, field
from functools import cache

from pymodbus.client import AsyncModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.logging import Log
from pymodbus.pdu import DecodePDU, ModbusPDU

from drivers import modbus_tcp
from drivers.backoff import Backoff
from drivers.bus_hub import BusHub, rtu_silence_s
from drivers.link_health import LinkHealth
from drivers.modbus_tcp import BUSY_BACKOFF_S
from drivers.register_map import DeviceRegisters, FieldCodec, ReadRequest, fault_meaning
from drivers.schema import TRANSMITTER_MAP, load_register_map

PARITIES = ("N", "E", "O")
#: Modbus exceptions with which a TCP gateway says "the device behind me did not answer".
GATEWAY_NO_DEVICE = frozenset({0x0A, 0x0B})
#: pymodbus's own reconnect task must never run: a delay so long it never fires
#: before we close the client (0 would disable it in 3.16 but busy-loops in others).
_LIBRARY_RECONNECT_DELAY_S = 24 * 3600.0
#: Silent requests pymodbus tolerates before closing the connection: never, we decide.
_LIBRARY_MAX_NO_RESPONSES = 2**31 - 1


class _ReplyDecoder(DecodePDU):
    """pymodbus's reply decoder without the debug text it builds for every reply.

    pymodbus 3.16 passes ``str(pdu)`` to its debug log call, so every reply is
    formatted as text even with debug logging off (a few per cent of the poll's
    CPU). With debug off, the plain replies (no sub-function) are decoded here the
    way the library does; everything else, and everything with debug on, goes to
    the library's own ``decode``.
    """

    def decode(self, frame: bytes) -> ModbusPDU | None:
        function_code = frame[0] if frame else 0
        if (
            function_code >= 0x80
            or function_code in self.pdu_sub_table
            or Log._logger.isEnabledFor(logging.DEBUG)
        ):
            return super().decode(frame)
        pdu_class = self.pdu_table.get(function_code, (None, None))[self.pdu_inx]
        if pdu_class is None:
            return super().decode(frame)
        pdu = pdu_class()
        try:
            pdu.decode(frame[1:])
        except (ModbusException, ValueError, IndexError, struct.error):
            return super().decode(frame)  # the library logs what was wrong
        return pdu


class ModbusRequestError(Exception):
    """A Modbus request failed; the message says where and why."""


class ModbusLinkLostError(ModbusRequestError):
    """The connection or port is unusable; it has to be reopened."""


class ModbusNoResponseError(ModbusRequestError):
    """One device did not answer (the link itself may be fine)."""


class ModbusRefusedError(ModbusRequestError):
    """The device answered with a Modbus exception."""

    def __init__(self, message: str, code: int | None) -> None:
        super().__init__(message)
        self.code = code


def read_steps(requests: Sequence[ReadRequest], device_id: int) -> tuple[modbus_tcp.Step, ...]:
    """A register map's read requests (one per contiguous block) as one chain group for
    ``device_id``: a device's whole read, for :meth:`ModbusConnection.read_chain`."""
    return tuple(
        modbus_tcp.read_step(r.function_code, r.address, r.count, device_id) for r in requests
    )


class ModbusConnection:
    """One Modbus client (TCP or RTU) whose life cycle the gateway owns.

    ``open()`` builds a new client every time, so nothing stale survives a lost
    connection; ``close()`` also cancels any reconnect task pymodbus started. A
    request ends after ``timeout_s × (retries + 1)`` at most and raises one of
    :class:`ModbusLinkLostError`, :class:`ModbusNoResponseError`, :class:`ModbusRefusedError`.
    Each attempt has one timeout (pymodbus's own timer on RTU; on TCP a deadline the
    connection's one timer checks, :mod:`drivers.modbus_tcp`); a request runs in the
    caller's task. On TCP, :meth:`read_chain` sends several devices' reads as one
    chain, each request written from the previous one's reply. Requests are never
    pipelined, although Modbus TCP would allow it: pymodbus's own server (3.16)
    answers only the first of two requests sent together, and many serial gateways
    do no better. The constructor does no I/O.
    """

    def __init__(
        self,
        *,
        tcp: tuple[str, int] | None = None,
        serial_port: str | None = None,
        baudrate: int = 19200,
        parity: str = "N",
        timeout_s: float = 1.0,
        retries: int = 0,
        name: str = "",
    ) -> None:
        if (tcp is None) == (serial_port is None):
            raise ValueError("give exactly one of tcp=(host, port) or serial_port=")
        if parity not in PARITIES:
            raise ValueError(f"parity must be one of {PARITIES}, got {parity!r}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        self._tcp = tcp
        self._serial_port = serial_port
        self._baudrate = baudrate
        self._parity = parity
        self.timeout_s = timeout_s
        self.retries = retries
        self._name = name
        self._client: AsyncModbusSerialClient | None = None
        self._wire: modbus_tcp.TcpTransactions | None = None
        self._busy_retries_before = 0  # of connections closed since
        #: Serial requests sent again after a busy reply (the bus that resends counts them).
        self.busy_retries_serial = 0
        where = f"TCP {tcp[0]}:{tcp[1]}" if tcp is not None else f"serial {serial_port}"
        self.where = f"{name} ({where})" if name else where

    @property
    def busy_retries(self) -> int:
        """Requests sent again because the device answered busy (exception 06)."""
        wire = self._wire
        tcp = self._busy_retries_before + (wire.busy_retries if wire is not None else 0)
        return tcp + self.busy_retries_serial

    @property
    def connected(self) -> bool:
        if self._wire is not None:
            return self._wire.connected
        return self._client is not None and self._client.connected

    def _make_client(self) -> AsyncModbusSerialClient:
        assert self._serial_port is not None
        return AsyncModbusSerialClient(
            self._serial_port,
            baudrate=self._baudrate,
            parity=self._parity,
            bytesize=8,
            stopbits=1,
            name=self._name or "gateway",
            timeout=self.timeout_s,
            retries=self.retries,
            reconnect_delay=_LIBRARY_RECONNECT_DELAY_S,
            reconnect_delay_max=_LIBRARY_RECONNECT_DELAY_S,
        )

    async def open(self) -> None:
        """Connect a new client (closing any old one); :class:`ModbusLinkLostError` on failure."""
        self.close()
        if self._tcp is not None:
            try:
                self._wire = await modbus_tcp.connect(*self._tcp, self.timeout_s + 0.5)
            except (OSError, TimeoutError) as exc:
                raise ModbusLinkLostError(f"{self.where}: cannot connect ({_text(exc)})") from exc
            return
        client = self._make_client()
        client.set_max_no_responses(_LIBRARY_MAX_NO_RESPONSES)
        client.ctx.framer.decoder = _ReplyDecoder(False)
        try:
            ok = await asyncio.wait_for(client.connect(), self.timeout_s + 0.5)
        except (OSError, TimeoutError, ModbusException) as exc:
            client.close()
            raise ModbusLinkLostError(f"{self.where}: cannot connect ({_text(exc)})") from exc
        except BaseException:
            client.close()
            raise
        if not ok or not client.connected:
            client.close()  # pymodbus only logs the reason (refused, unreachable, timeout)
            raise ModbusLinkLostError(
                f"{self.where}: cannot connect (refused, or no answer in {self.timeout_s:g} s)"
            )
        self._client = client

    def close(self) -> None:
        """Close the client (idempotent); also stops pymodbus's reconnect task."""
        client, self._client = self._client, None
        if client is not None:
            client.close()
        wire, self._wire = self._wire, None
        if wire is not None:
            self._busy_retries_before += wire.busy_retries
            wire.close()

    async def read_input_registers(self, address: int, count: int, device_id: int) -> list[int]:
        if self._tcp is not None:
            return await self._tcp_read(modbus_tcp.read_step(4, address, count, device_id))
        client = self._usable_client()
        response = await self._execute(
            client,
            device_id,
            client.read_input_registers(address, count=count, device_id=device_id),
        )
        return self._registers(response, count, device_id)

    async def read_holding_registers(self, address: int, count: int, device_id: int) -> list[int]:
        if self._tcp is not None:
            return await self._tcp_read(modbus_tcp.read_step(3, address, count, device_id))
        client = self._usable_client()
        response = await self._execute(
            client,
            device_id,
            client.read_holding_registers(address, count=count, device_id=device_id),
        )
        return self._registers(response, count, device_id)

    def read(self, request: ReadRequest, device_id: int) -> Awaitable[list[int]]:
        """One block of a register map."""
        if self._tcp is not None:
            code, address, count = request.function_code, request.address, request.count
            return self._tcp_read(modbus_tcp.read_step(code, address, count, device_id))
        if request.register_type == "input":
            return self.read_input_registers(request.address, request.count, device_id)
        return self.read_holding_registers(request.address, request.count, device_id)

    async def write_registers(self, address: int, values: list[int], device_id: int) -> None:
        """FC16 write of ``values`` from ``address``."""
        if self._tcp is not None:
            step = modbus_tcp.step(modbus_tcp.write_pdu(address, values), device_id)
            reply = self._raise(await self._tcp_groups(((step,),)), device_id)
            assert isinstance(reply, bytes)
            self._check_reply(reply, device_id)
            return
        client = self._usable_client()
        await self._execute(
            client, device_id, client.write_registers(address, values, device_id=device_id)
        )

    # -- TCP: chains of requests on drivers.modbus_tcp ---------------------------------

    @property
    def chains(self) -> bool:
        """Whether :meth:`read_chain` is available: on TCP, where the protocol sends each
        request from the previous one's reply (one request on the wire at a time)."""
        return self._tcp is not None

    async def read_chain(
        self, groups: Sequence[Sequence[modbus_tcp.Step]]
    ) -> list[list[int] | ModbusRequestError]:
        """TCP: each group's read requests in turn (:func:`drivers.modbus_tcp.read_step`,
        one group per device), as one chain on the wire; per group its registers
        concatenated, or the error that ended it (:class:`ModbusLinkLostError` for it and
        every later group once the connection is gone). Each request keeps its own
        timeout and ``retries``; a failed group does not stop the next one."""
        outcomes = await self._tcp_groups(groups)
        results: list[list[int] | ModbusRequestError] = []
        for outcome, group in zip(outcomes, groups, strict=True):
            if type(outcome) is list:
                results.append(outcome)
            else:
                results.append(self._error(outcome, group[0].device_id))
        return results

    async def _tcp_read(self, step: modbus_tcp.Step) -> list[int]:
        registers = self._raise(await self._tcp_groups(((step,),)), step.device_id)
        assert isinstance(registers, list)
        return registers

    def _tcp_groups(
        self, groups: Sequence[Sequence[modbus_tcp.Step]]
    ) -> asyncio.Future[list[modbus_tcp.Outcome]]:
        wire = self._wire
        if wire is None or not wire.connected:
            raise ModbusLinkLostError(f"{self.where}: connection lost")
        return wire.submit(groups, self.timeout_s, self.retries)

    def _raise(self, outcomes: list[modbus_tcp.Outcome], device_id: int) -> list[int] | bytes:
        """A one-group chain's outcome, or its error raised."""
        outcome = outcomes[0]
        if isinstance(outcome, list | bytes):
            return outcome
        raise self._error(outcome, device_id) from outcome

    def _error(self, outcome: modbus_tcp.Outcome, device_id: int) -> ModbusRequestError:
        """The gateway's error for a failed group of requests to ``device_id``."""
        if isinstance(outcome, TimeoutError):
            return ModbusNoResponseError(
                f"no response from device {device_id} on {self.where} "
                f"within {self.timeout_s * (self.retries + 1):g} s"
            )
        if isinstance(outcome, ConnectionError):
            return ModbusLinkLostError(f"{self.where}: {outcome}")
        if isinstance(outcome, modbus_tcp.ReplyError):
            try:
                self._check_reply(outcome.pdu, device_id)
            except ModbusRequestError as exc:
                return exc
            return ModbusNoResponseError(
                f"device {device_id} on {self.where}: unexpected reply {outcome.pdu.hex()}"
            )
        detail = f"unexpected reply {outcome.hex()}" if isinstance(outcome, bytes) else outcome
        return ModbusNoResponseError(f"device {device_id} on {self.where}: {detail}")

    def _check_reply(self, reply: bytes, device_id: int) -> None:
        """A reply other than registers: decoded by pymodbus; an exception reply raises."""
        response = _REPLY_DECODER.decode(reply)
        if response is None:
            raise ModbusNoResponseError(f"bad reply from device {device_id}: {reply.hex()}")
        self._refusal(response, device_id)

    # -- RTU: pymodbus's serial client -------------------------------------------------

    def _registers(self, response: ModbusPDU, count: int, device_id: int) -> list[int]:
        registers = response.registers
        if len(registers) != count:
            raise ModbusNoResponseError(
                f"device {device_id} on {self.where}: {len(registers)} registers in the "
                f"reply, {count} asked"
            )
        return list(registers)

    def _usable_client(self) -> AsyncModbusSerialClient:
        client = self._client
        if client is None or not client.connected:
            raise ModbusLinkLostError(f"{self.where}: connection lost")
        return client

    async def _execute(
        self,
        client: AsyncModbusSerialClient,
        device_id: int,
        request: Awaitable[ModbusPDU],
    ) -> ModbusPDU:
        try:
            response = await request
        except ConnectionException as exc:
            raise ModbusLinkLostError(f"{self.where}: connection lost ({exc})") from exc
        except ModbusIOException as exc:
            if not client.connected:
                raise ModbusLinkLostError(f"{self.where}: connection lost") from exc
            if "no response" in str(exc).lower():
                raise ModbusNoResponseError(
                    f"no response from device {device_id} on {self.where} "
                    f"within {self.timeout_s * (self.retries + 1):g} s"
                ) from exc
            raise ModbusNoResponseError(f"bad reply from device {device_id}: {exc}") from exc
        except (OSError, TimeoutError) as exc:
            raise ModbusLinkLostError(f"{self.where}: request failed ({_text(exc)})") from exc
        self._refusal(response, device_id)
        return response

    def _refusal(self, response: ModbusPDU, device_id: int) -> None:
        """Raise for an exception reply: a gateway's "no device" or the device's refusal."""
        if not response.isError():
            return
        code = getattr(response, "exception_code", None)
        if code in GATEWAY_NO_DEVICE:
            raise ModbusNoResponseError(
                f"no response from device {device_id} on {self.where} "
                f"(gateway exception {code:#04x})"
            )
        if code == modbus_tcp.DEVICE_BUSY:
            raise ModbusRefusedError(
                f"device {device_id} on {self.where} stayed busy (exception 06) when asked "
                f"again {len(BUSY_BACKOFF_S)} times: no reading",
                code,
            )
        raise ModbusRefusedError(
            f"device {device_id} on {self.where} refused the request (exception {code})",
            code,
        )


#: Decodes the TCP replies that are not register reads (FC16 echoes, exception replies).
_REPLY_DECODER = _ReplyDecoder(False)


@cache
def _shipped(name: str) -> DeviceRegisters:
    return DeviceRegisters(load_register_map(name))


@dataclass
class _DecodeMemo:
    """A device's last registers and results, and per sensor its last (raw, status, result)."""

    registers: list[int] = field(default_factory=list)
    results: dict[str, ChannelResult] = field(default_factory=dict)
    channels: dict[str, tuple[float, int | None, ChannelResult]] = field(default_factory=dict)


@dataclass(frozen=True)
class DeviceMap:
    """One input module: its device id, the sensor wired to each channel, its register map.

    ``channels[i]`` is the sensor on the map's channel i+1; ``None`` (or a missing
    trailing entry) is a channel without a probe, which is not reported.
    ``registers`` is the device's register map ready for the wire (by default the
    8-channel Pt100 module, ``drivers/maps/pt100_8ch.yaml``).
    """

    device_id: int
    channels: tuple[str | None, ...]
    registers: DeviceRegisters = field(
        default_factory=lambda: _shipped(TRANSMITTER_MAP), compare=False, repr=False
    )
    #: What :func:`decode_channels` decoded last, to reuse what did not change.
    memo: _DecodeMemo = field(default_factory=lambda: _DecodeMemo(), compare=False, repr=False)

    def __post_init__(self) -> None:
        if not 1 <= self.device_id <= 247:
            raise ValueError(f"device id {self.device_id} is outside the Modbus range 1–247")
        available = len(self.registers.channels)
        if len(self.channels) > available:
            raise ValueError(
                f"device {self.device_id}: {len(self.channels)} channels, its register map "
                f"{self.registers.map.label} has {available}"
            )
        object.__setattr__(self, "channels", tuple(self.channels))

    @property
    def sensors(self) -> list[str]:
        return [name for name in self.channels if name is not None]


@dataclass(frozen=True)
class ChannelResult:
    """One sensor's reading in one cycle.

    ``value_C`` is None whenever there is no valid temperature: the device did not
    answer (``status`` None, ``error`` says why), or it reported a fault (``status``
    is its code, ``error`` names it). A good reading has status 0 and no error.
    """

    sensor: str
    value_C: float | None
    status: int | None
    error: str | None


def decode_channels(device: DeviceMap, registers: Sequence[int]) -> dict[str, ChannelResult]:
    """The replies to a device's read requests (concatenated) → a result per wired sensor.

    Under the map's fault convention, a status other than ``ok`` is that fault;
    a value code (the Pt100 module's 32767 and −32768) is never a temperature,
    even with status OK: a clamped reading has the same counts, so only the status
    tells them apart, and a module that says OK next to a fault code is not to be
    trusted. Without a status field, a value code is the fault it names.
    A channel whose raw value and status are those of the previous call keeps its
    previous (immutable) result object.
    """
    memo = device.memo
    if memo.results and memo.registers == registers:
        return dict(memo.results)
    layout = device.registers
    raws = layout.decode_raw(registers)
    results: dict[str, ChannelResult] = {}
    for codec, sensor in zip(layout.channels, device.channels, strict=False):
        if sensor is None:
            continue
        raw = raws[codec.name]
        status = int(raws[codec.status]) if codec.status is not None else None
        previous = memo.channels.get(sensor)
        if previous is not None and previous[0] == raw and previous[1] == status:
            results[sensor] = previous[2]
            continue
        results[sensor] = _channel_result(layout, codec, sensor, raw, status)
        memo.channels[sensor] = (raw, status, results[sensor])
    memo.registers, memo.results = list(registers), results
    return dict(results)


def _channel_result(
    layout: DeviceRegisters, codec: FieldCodec, sensor: str, raw: float, status: int | None
) -> ChannelResult:
    """One channel's result from its raw value and status, under the map's fault convention."""
    faults = layout.faults
    if faults is None:
        return ChannelResult(sensor, codec.value(raw), None, None)
    ok = layout.ok_status
    code_name = layout.value_code_names.get(raw)
    if status is not None:
        if status != ok:
            text = layout.status_texts.get(status, f"unknown status {status}")
            return ChannelResult(sensor, None, status, text)
        if code_name is not None:
            return ChannelResult(sensor, None, status, f"fault code {_number(raw)} with status OK")
    elif code_name is not None:
        status_code = faults.status_codes.get(code_name)
        return ChannelResult(sensor, None, status_code, fault_meaning(code_name))
    return ChannelResult(sensor, codec.value(raw), ok, None)


def _number(raw: float) -> str:
    return str(int(raw)) if float(raw).is_integer() else repr(raw)


@dataclass
class _DeviceRead:
    """How far one device's read has come in a cycle on an RTU bus: its next request,
    the registers so far, and how often the current request was answered busy."""

    device: DeviceMap
    index: int = 0
    registers: list[int] = field(default_factory=list)
    busy: int = 0
    ask_at: float = 0.0


@dataclass
class _Cycle:
    """What happened on the bus during one ``read_all``."""

    results: dict[str, ChannelResult] = field(default_factory=dict)
    answered: bool = False
    lost: str | None = None


class TransmitterBus:
    """One RS-485 bus (Modbus RTU) or one TCP gateway with several modules behind it.

    Each ``read_all`` sends each device's read requests in turn (a bus carries one
    request at a time): one per contiguous block of its register map, so one FC4
    request of 16 registers for the Pt100 module. Over TCP (no inter-frame silence,
    no device asking for a pause) the whole cycle's requests are one chain on the
    connection (:meth:`ModbusConnection.read_chain`). A silent device costs one timeout
    (``timeout_s × (retries + 1)``) and does not close the port for the others. The
    connection is dropped and reopened after a :class:`Backoff` when it breaks, and
    also when no device at all answered in a cycle: that is how a half-open TCP
    connection or a re-plugged cable (no error, just silence) is recovered.

    The port itself belongs to a :class:`drivers.bus_hub.BusHub`: give ``hub`` when
    several buses (machines) share one RS-485 line, and each ``read_all`` is then one
    turn under the hub's lock; without it the bus has a hub of its own.

    ``health`` is the bus's, ``device_health[device_id]`` each module's. Times are
    the caller's ``now_s`` (monotonic seconds); the backoff counts in them too.
    """

    def __init__(
        self,
        devices: Sequence[DeviceMap],
        *,
        tcp: tuple[str, int] | None = None,
        serial_port: str | None = None,
        baudrate: int = 19200,
        parity: str = "N",
        timeout_s: float = 0.3,
        retries: int = 0,
        name: str = "",
        backoff: Backoff | None = None,
        hub: BusHub | None = None,
    ) -> None:
        if not devices:
            raise ValueError("a transmitter bus needs at least one device")
        ids = [device.device_id for device in devices]
        if len(set(ids)) != len(ids):
            raise ValueError(f"device ids must be unique on one bus, got {ids}")
        sensors = [sensor for device in devices for sensor in device.sensors]
        if len(set(sensors)) != len(sensors):
            raise ValueError(f"sensor names must be unique on one bus, got {sensors}")
        if hub is None:
            link = ModbusConnection(
                tcp=tcp,
                serial_port=serial_port,
                baudrate=baudrate,
                parity=parity,
                timeout_s=timeout_s,
                retries=retries,
                name=name,
            )
            silence_s = rtu_silence_s(baudrate) if serial_port is not None else 0.0
            hub = BusHub(link, silence_s=silence_s, backoff=backoff)
        self._hub = hub
        self._devices = tuple(devices)
        self._chain = self._plan_chain()
        self._lock = asyncio.Lock()
        self.health = LinkHealth()
        self.device_health: dict[int, LinkHealth] = {d.device_id: LinkHealth() for d in devices}

    @property
    def where(self) -> str:
        return self._hub.where

    @property
    def hub(self) -> BusHub:
        return self._hub

    @property
    def devices(self) -> tuple[DeviceMap, ...]:
        return self._devices

    async def read_all(self, now_s: float) -> dict[str, ChannelResult]:
        """Read every device once; a result for every wired sensor, never an exception
        for a field fault. Concurrent calls are served one after the other."""
        async with self._lock:
            return await self._read_all(now_s)

    async def _read_all(self, now_s: float) -> dict[str, ChannelResult]:
        async with self._hub.transaction(self, now_s) as turn:
            if turn.failure is not None:
                self.health.record_failure(turn.failure)
                return self._all_failed(turn.failure)
            if turn.reopened:
                self.health.record_connect()
            cycle = _Cycle()
            if self._chain is not None:
                await self._read_chained(self._chain, now_s, cycle)
            else:
                await self._read_in_turn(now_s, cycle)
            turn.report(answered=cycle.answered, lost=cycle.lost)
        if cycle.lost is None and not cycle.answered:
            cycle.lost = f"{self.where}: no device answered"
        if cycle.lost is not None:
            self.health.record_failure(cycle.lost)
        else:
            self.health.record_ok(now_s)
        return cycle.results

    def _plan_chain(self) -> tuple[tuple[modbus_tcp.Step, ...], ...] | None:
        """Every device's read requests as one chain of groups (one group per device),
        when the link runs chains (TCP) and no silence or pause is to be kept between
        requests; else None, and each request goes through the hub on its own."""
        link = self._hub.link
        if not isinstance(link, ModbusConnection) or not link.chains or self._hub.silence_s > 0:
            return None
        if any(d.registers.workarounds.pause_between_requests_s > 0 for d in self._devices):
            return None
        return tuple(
            read_steps(device.registers.requests, device.device_id) for device in self._devices
        )

    async def _read_chained(
        self, chain: tuple[tuple[modbus_tcp.Step, ...], ...], now_s: float, cycle: _Cycle
    ) -> None:
        """All devices in one chain on the connection: one future for the bus's cycle."""
        self._hub.requests += sum(len(group) for group in chain)
        try:
            results = await self._link.read_chain(chain)
        except ModbusLinkLostError as exc:
            results = [exc] * len(chain)
        for device, result in zip(self._devices, results, strict=True):
            self._record(device, now_s, cycle, result)

    async def _read_in_turn(self, now_s: float, cycle: _Cycle) -> None:
        """Each device's requests in turn, each through the hub (RTU, or TCP with pauses).

        On RTU, a device that answers busy (exception 06) is asked again after a back-off of
        5, 15, then 30 ms (:data:`drivers.modbus_tcp.BUSY_BACKOFF_S`, as on TCP); while
        it waits, the bus reads the devices after it, so the back-off does not keep the
        line idle while there is other work on it. The turn ends when every device has
        its registers or its error: a device still busy after the last resend has no
        reading this cycle.
        """
        loop = asyncio.get_running_loop()
        waiting: list[_DeviceRead] = []
        for device in self._devices:
            await self._read_device(_DeviceRead(device), now_s, cycle, waiting)
        while waiting:
            read = min(waiting, key=lambda r: r.ask_at)
            waiting.remove(read)
            if (wait_s := read.ask_at - loop.time()) > 0 and cycle.lost is None:
                await asyncio.sleep(wait_s)
            await self._read_device(read, now_s, cycle, waiting)

    async def _read_device(
        self, read: _DeviceRead, now_s: float, cycle: _Cycle, waiting: list[_DeviceRead]
    ) -> None:
        """Go on with one device's requests; if it answered busy, it joins ``waiting``."""
        device = read.device
        if cycle.lost is not None:  # the link broke earlier in this cycle
            self._record(device, now_s, cycle, None)
            return
        try:
            done = await self._read_requests(read)
        except ModbusRequestError as exc:
            self._record(device, now_s, cycle, exc)
            return
        if done:
            self._record(device, now_s, cycle, read.registers)
        else:
            waiting.append(read)

    def _record(
        self,
        device: DeviceMap,
        now_s: float,
        cycle: _Cycle,
        result: list[int] | ModbusRequestError | None,
    ) -> None:
        """One device's outcome into the cycle's results and its health (None: not read,
        the link broke earlier in the cycle)."""
        health = self.device_health[device.device_id]
        if cycle.lost is not None:
            health.record_failure(cycle.lost)
            cycle.results.update(_failed(device, cycle.lost))
            return
        if isinstance(result, list):
            cycle.answered = True
            health.record_ok(now_s)
            cycle.results.update(decode_channels(device, result))
            return
        assert result is not None
        if isinstance(result, ModbusLinkLostError):
            cycle.lost = str(result)
        elif isinstance(result, ModbusRefusedError):
            cycle.answered = True  # the device is there, it just said no
        error = str(result)
        health.record_failure(error)
        cycle.results.update(_failed(device, error))

    @property
    def _link(self) -> ModbusConnection:
        link = self._hub.link
        assert isinstance(link, ModbusConnection)
        return link

    async def _read_requests(self, read: _DeviceRead) -> bool:
        """The device's read requests (one per contiguous block) from where ``read`` left
        off, replies concatenated into ``read.registers``: True when all are in, False when
        the device answered busy and is to be asked again at ``read.ask_at``.

        A device whose workarounds ask for a pause between requests gets it from the
        hub, as a longer inter-frame silence before each of its requests.
        """
        layout = read.device.registers
        link = self._link
        device_id = read.device.device_id
        pause_s = layout.workarounds.pause_between_requests_s
        requests = layout.requests
        while read.index < len(requests):
            request = requests[read.index]
            try:
                read.registers += await self._hub.request(
                    functools.partial(link.read, request, device_id), pause_s=pause_s
                )
            except ModbusRefusedError as exc:
                # TCP's own wire has asked again already (drivers.modbus_tcp).
                busy = exc.code == modbus_tcp.DEVICE_BUSY and not link.chains
                if not busy or read.busy >= len(BUSY_BACKOFF_S):
                    raise
                read.ask_at = asyncio.get_running_loop().time() + BUSY_BACKOFF_S[read.busy]
                read.busy += 1
                link.busy_retries_serial += 1
                return False
            read.index += 1
            read.busy = 0
        return True

    def _all_failed(self, reason: str) -> dict[str, ChannelResult]:
        results: dict[str, ChannelResult] = {}
        for device in self._devices:
            self.device_health[device.device_id].record_failure(reason)
            results.update(_failed(device, reason))
        return results

    async def close(self) -> None:
        """Leave the hub (idempotent): the port closes with its last user; a later
        read_all reopens it."""
        self._hub.detach(self)
        self.health.connected = False


def _failed(device: DeviceMap, error: str) -> dict[str, ChannelResult]:
    return {sensor: ChannelResult(sensor, None, None, error) for sensor in device.sensors}


def _text(exc: BaseException) -> str:
    """An exception's text, or its type name when it has none (a bare timeout)."""
    return str(exc) or type(exc).__name__
