"""Temperature transmitters over Modbus RTU or TCP, and the gateway's one pymodbus client.

Pt100 input modules (8 channels each, one device id per module, several per RS-485
bus or behind one TCP port) report 0.1 °C counts and a status per channel; the map
is ``simulator/servers/MODBUS.md``. :class:`TransmitterBus` reads every module once per
cycle and never raises for a field fault: each channel comes back with a value or
with the reason it has none.

:class:`ModbusConnection` is the only place in the gateway that uses pymodbus (the
CNC Modbus driver builds on it too), so the next pymodbus API change is fixed once.
It owns the client's life cycle instead of relying on pymodbus's: the library does
not reconnect after a cable re-plug (#1635), busy-loops with ``reconnect_delay=0``
(#1794) and closes the whole port after a few silent requests, taking every other
slave on the bus down with one dead one (#1654).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field

from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from drivers.backoff import Backoff
from drivers.bus_hub import BusHub, rtu_silence_s
from drivers.link_health import LinkHealth
from drivers.register_codec import OPEN_CIRCUIT_CODE, SHORT_CIRCUIT_CODE

CHANNELS = 8
#: Input registers (FC4): 0–7 channel values (int16, 0.1 °C), 8–15 channel statuses.
REGISTER_COUNT = 2 * CHANNELS
STATUS_OK = 0
STATUS_TEXT = {1: "open circuit", 2: "short circuit", 3: "out of range"}
#: Value-register fault codes (signed view); never a reading when the status says OK.
FAULT_CODES = frozenset({OPEN_CIRCUIT_CODE, SHORT_CIRCUIT_CODE})
PARITIES = ("N", "E", "O")
#: Modbus exceptions with which a TCP gateway says "the device behind me did not answer".
GATEWAY_NO_DEVICE = frozenset({0x0A, 0x0B})
#: pymodbus's own reconnect task must never run: a delay so long it never fires
#: before we close the client (0 would disable it in 3.16 but busy-loops in others).
_LIBRARY_RECONNECT_DELAY_S = 24 * 3600.0
#: Silent requests pymodbus tolerates before closing the connection: never, we decide.
_LIBRARY_MAX_NO_RESPONSES = 2**31 - 1


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


class ModbusConnection:
    """One pymodbus async client (TCP or RTU) whose life cycle the gateway owns.

    ``open()`` builds a new client every time, so nothing stale survives a lost
    connection; ``close()`` also cancels any reconnect task pymodbus started. A
    request ends after ``timeout_s × (retries + 1)`` at most and raises one of
    :class:`ModbusLinkLostError`, :class:`ModbusNoResponseError`, :class:`ModbusRefusedError`.
    The constructor does no I/O.
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
        self._client: AsyncModbusTcpClient | AsyncModbusSerialClient | None = None
        where = f"TCP {tcp[0]}:{tcp[1]}" if tcp is not None else f"serial {serial_port}"
        self.where = f"{name} ({where})" if name else where

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.connected

    @property
    def _request_bound_s(self) -> float:
        """Backstop for one request: pymodbus's own limit plus a margin."""
        return self.timeout_s * (self.retries + 1) + 0.5

    def _make_client(self) -> AsyncModbusTcpClient | AsyncModbusSerialClient:
        name = self._name or "gateway"
        if self._tcp is not None:
            host, port = self._tcp
            return AsyncModbusTcpClient(
                host,
                port=port,
                name=name,
                timeout=self.timeout_s,
                retries=self.retries,
                reconnect_delay=_LIBRARY_RECONNECT_DELAY_S,
                reconnect_delay_max=_LIBRARY_RECONNECT_DELAY_S,
            )
        assert self._serial_port is not None
        return AsyncModbusSerialClient(
            self._serial_port,
            baudrate=self._baudrate,
            parity=self._parity,
            bytesize=8,
            stopbits=1,
            name=name,
            timeout=self.timeout_s,
            retries=self.retries,
            reconnect_delay=_LIBRARY_RECONNECT_DELAY_S,
            reconnect_delay_max=_LIBRARY_RECONNECT_DELAY_S,
        )

    async def open(self) -> None:
        """Connect a new client (closing any old one); :class:`ModbusLinkLostError` on failure."""
        self.close()
        client = self._make_client()
        client.set_max_no_responses(_LIBRARY_MAX_NO_RESPONSES)
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

    async def read_input_registers(self, address: int, count: int, device_id: int) -> list[int]:
        response = await self._execute(
            device_id,
            lambda c: c.read_input_registers(address, count=count, device_id=device_id),
        )
        return self._registers(response, count, device_id)

    async def read_holding_registers(self, address: int, count: int, device_id: int) -> list[int]:
        response = await self._execute(
            device_id,
            lambda c: c.read_holding_registers(address, count=count, device_id=device_id),
        )
        return self._registers(response, count, device_id)

    async def write_registers(self, address: int, values: list[int], device_id: int) -> None:
        """FC16 write of ``values`` from ``address``."""
        await self._execute(
            device_id,
            lambda c: c.write_registers(address, values, device_id=device_id),
        )

    def _registers(self, response: ModbusPDU, count: int, device_id: int) -> list[int]:
        registers = list(response.registers)
        if len(registers) != count:
            raise ModbusNoResponseError(
                f"device {device_id} on {self.where}: {len(registers)} registers in the "
                f"reply, {count} asked"
            )
        return registers

    async def _execute(
        self,
        device_id: int,
        request: Callable[[AsyncModbusTcpClient | AsyncModbusSerialClient], Awaitable[ModbusPDU]],
    ) -> ModbusPDU:
        client = self._client
        if client is None or not client.connected:
            raise ModbusLinkLostError(f"{self.where}: connection lost")
        try:
            response = await asyncio.wait_for(request(client), self._request_bound_s)
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
            # pymodbus's own timeout did not end the request: the client is wedged.
            raise ModbusLinkLostError(f"{self.where}: request hung ({_text(exc)})") from exc
        if response.isError():
            code = getattr(response, "exception_code", None)
            if code in GATEWAY_NO_DEVICE:
                raise ModbusNoResponseError(
                    f"no response from device {device_id} on {self.where} "
                    f"(gateway exception {code:#04x})"
                )
            raise ModbusRefusedError(
                f"device {device_id} on {self.where} refused the request (exception {code})",
                code,
            )
        return response


@dataclass(frozen=True)
class DeviceMap:
    """One input module: its device id and the sensor name wired to each channel.

    ``channels[i]`` is the sensor on channel i+1; ``None`` (or a missing trailing
    entry) is a channel without a probe, which is not reported.
    """

    device_id: int
    channels: tuple[str | None, ...]

    def __post_init__(self) -> None:
        if not 1 <= self.device_id <= 247:
            raise ValueError(f"device id {self.device_id} is outside the Modbus range 1–247")
        if len(self.channels) > CHANNELS:
            raise ValueError(
                f"device {self.device_id}: {len(self.channels)} channels, a module has {CHANNELS}"
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
    """The 16 input registers of one module → a result per wired sensor.

    A fault code in the value register is never a temperature, even with status OK:
    a clamped reading has the same counts, so only the status tells them apart, and
    a module that says OK next to a fault code is not to be trusted.
    """
    results: dict[str, ChannelResult] = {}
    for index, sensor in enumerate(device.channels):
        if sensor is None:
            continue
        raw, status = registers[index], registers[CHANNELS + index]
        counts = raw - 0x10000 if raw & 0x8000 else raw
        if status != STATUS_OK:
            text = STATUS_TEXT.get(status, f"unknown status {status}")
            results[sensor] = ChannelResult(sensor, None, status, text)
        elif counts in FAULT_CODES:
            results[sensor] = ChannelResult(
                sensor, None, status, f"fault code {counts} with status OK"
            )
        else:
            results[sensor] = ChannelResult(sensor, counts / 10, status, None)
    return results


@dataclass
class _Cycle:
    """What happened on the bus during one ``read_all``."""

    results: dict[str, ChannelResult] = field(default_factory=dict)
    answered: bool = False
    lost: str | None = None


class TransmitterBus:
    """One RS-485 bus (Modbus RTU) or one TCP gateway with several modules behind it.

    Each ``read_all`` sends one FC4 request (16 registers) per device, in turn (a bus
    carries one request at a time). A silent device costs one timeout
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
            for device in self._devices:
                await self._read_device(device, now_s, cycle)
            turn.report(answered=cycle.answered, lost=cycle.lost)
        if cycle.lost is None and not cycle.answered:
            cycle.lost = f"{self.where}: no device answered"
        if cycle.lost is not None:
            self.health.record_failure(cycle.lost)
        else:
            self.health.record_ok(now_s)
        return cycle.results

    async def _read_device(self, device: DeviceMap, now_s: float, cycle: _Cycle) -> None:
        health = self.device_health[device.device_id]
        if cycle.lost is not None:  # the link broke earlier in this cycle
            health.record_failure(cycle.lost)
            cycle.results.update(_failed(device, cycle.lost))
            return
        try:
            registers = await self._hub.request(
                lambda: self._link.read_input_registers(0, REGISTER_COUNT, device.device_id)
            )
        except ModbusLinkLostError as exc:
            cycle.lost = str(exc)
            error = str(exc)
        except ModbusRefusedError as exc:
            cycle.answered = True  # the device is there, it just said no
            error = str(exc)
        except ModbusNoResponseError as exc:
            error = str(exc)
        else:
            cycle.answered = True
            health.record_ok(now_s)
            cycle.results.update(decode_channels(device, registers))
            return
        health.record_failure(error)
        cycle.results.update(_failed(device, error))

    @property
    def _link(self) -> ModbusConnection:
        link = self._hub.link
        assert isinstance(link, ModbusConnection)
        return link

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
