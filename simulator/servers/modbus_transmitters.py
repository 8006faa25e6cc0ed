"""Simulated 8-channel Pt100 temperature transmitters: Modbus RTU or TCP slaves.

A spindle's temperature sensors reach the gateway through input modules like these,
several on one RS-485 bus (one device id each) or behind a Modbus TCP port. The
simulator serves the machine's channel readings with the same register map, fault
codes and refusals as such a module, so the gateway's Modbus driver is tested
against what it will meet in the cabinet. The map is documented in MODBUS.md.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from simulator.link import MachineLink, MachineSnapshot
from simulator.servers.modbus_common import (
    BIT_FUNCTION_CODES,
    ModbusEndpoint,
    bit_table_placeholders,
    encode_temperature,
    is_internal_write,
    known_devices_only,
)

CHANNELS = 8
#: Input registers (FC4): 0–7 channel values (int16, 0.1 °C), 8–15 channel statuses.
VALUE_REGISTER = 0
STATUS_REGISTER = CHANNELS
#: Holding registers (FC3), read-only: channel count, resolution (0.001 °C/count), firmware.
INFO_REGISTERS = (CHANNELS, 100, 100)
PARITIES = ("N", "E", "O")


@dataclass(frozen=True)
class TransmitterDevice:
    """One input module: its Modbus device id and which sensor is wired to each channel.

    ``channels[i]`` names the key in ``MachineSnapshot.channels`` that channel i+1
    reports; ``None`` (or a missing trailing entry) is a channel with no probe, which a
    real module reports as open circuit.
    """

    device_id: int
    channels: Sequence[str | None]

    def __post_init__(self) -> None:
        if not 1 <= self.device_id <= 247:
            raise ValueError(f"device id {self.device_id} is outside the Modbus range 1–247")
        if len(self.channels) > CHANNELS:
            raise ValueError(
                f"device {self.device_id}: {len(self.channels)} channels given, "
                f"a module has {CHANNELS}"
            )
        padded = tuple(self.channels) + (None,) * (CHANNELS - len(self.channels))
        object.__setattr__(self, "channels", padded)

    def input_registers(self, snapshot: MachineSnapshot) -> list[int]:
        """The 16 input registers (values then statuses) this module shows for a snapshot.

        A sensor name the snapshot does not contain reads like an unplugged probe, as
        the module cannot know the sensor exists.
        """
        values: list[int] = []
        statuses: list[int] = []
        for name in self.channels:
            reading = snapshot.channels.get(name) if name is not None else None
            value, status = encode_temperature(reading)
            values.append(value)
            statuses.append(status)
        return values + statuses


class TransmitterServer(ModbusEndpoint):
    """Several transmitter modules on one serial bus (Modbus RTU) or one TCP port.

    Registers change only in ``publish()``, like a module that refreshes its
    registers once per conversion cycle; the caller decides the cycle.
    """

    def __init__(
        self,
        link: MachineLink,
        devices: Sequence[TransmitterDevice],
        *,
        tcp: tuple[str, int] | None = None,
        serial_port: str | None = None,
        baudrate: int = 19200,
        parity: str = "N",
    ) -> None:
        super().__init__()
        if (tcp is None) == (serial_port is None):
            raise ValueError("give exactly one of tcp=(host, port) or serial_port=")
        if not devices:
            raise ValueError("a transmitter server needs at least one device")
        ids = [device.device_id for device in devices]
        if len(set(ids)) != len(ids):
            raise ValueError(f"device ids must be unique on one bus, got {ids}")
        if parity not in PARITIES:
            raise ValueError(f"parity must be one of {PARITIES}, got {parity!r}")
        self._link = link
        self._devices = tuple(devices)
        self.silenced: set[int] = set()  # device ids that do not answer (a dead slave)
        #: Requests received per device id (answered or not): what the bus carried.
        self.requests: Counter[int] = Counter()
        self._tcp = tcp
        self._serial_port = serial_port
        self._baudrate = baudrate
        self._parity = parity

    @property
    def devices(self) -> tuple[TransmitterDevice, ...]:
        return self._devices

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) of a TCP server; the real port once started when port 0 was asked."""
        if self._tcp is None:
            raise AttributeError("a serial transmitter server has no TCP address")
        return self._bound_tcp_address(self._tcp)

    @property
    def serial_port(self) -> str | None:
        return self._serial_port

    def _describe(self) -> str:
        where = f"TCP {self._tcp[0]}:{self._tcp[1]}" if self._tcp else f"serial {self._serial_port}"
        return f"transmitter server on {where}"

    def _make_server(self) -> ModbusTcpServer | ModbusSerialServer:
        sim_devices = [
            SimDevice(id=device.device_id, simdata=_register_tables(), action=_module_action)
            for device in self._devices
        ]
        answer_known = known_devices_only(
            [device.device_id for device in self._devices], self.silenced
        )

        def trace_pdu(sending: bool, pdu: ModbusPDU) -> ModbusPDU:
            if not sending:
                self.requests[pdu.dev_id] += 1
            return answer_known(sending, pdu)

        if self._tcp is not None:
            return ModbusTcpServer(sim_devices, address=self._tcp, trace_pdu=trace_pdu)
        assert self._serial_port is not None
        return ModbusSerialServer(
            sim_devices,
            port=self._serial_port,
            baudrate=self._baudrate,
            parity=self._parity,
            bytesize=8,
            stopbits=1,
            trace_pdu=trace_pdu,
        )

    async def publish(self) -> None:
        """Copy the link's current channel readings into every module's input registers.

        Runs without yielding to the event loop, so a client never reads a half-updated
        module (or modules from two different snapshots).
        """
        server = self._require_server()
        snapshot = self._link.snapshot()
        for device in self._devices:
            await server.async_setValues(
                device.device_id, 4, VALUE_REGISTER, device.input_registers(snapshot)
            )


def _register_tables() -> tuple[list[SimData], list[SimData], list[SimData], list[SimData]]:
    """Separate holding and input tables (a plain list would alias FC3 and FC4)."""
    coils, discrete_inputs = bit_table_placeholders()
    holding = [SimData(0, values=list(INFO_REGISTERS), datatype=DataType.REGISTERS, readonly=True)]
    inputs = [SimData(0, count=2 * CHANNELS, values=0, datatype=DataType.REGISTERS)]
    return coils, discrete_inputs, holding, inputs


async def _module_action(
    function_code: int,
    _start_address: int,
    _address: int,
    _count: int,
    _registers: list[int],
    values: list[int] | list[bool] | None,
) -> ExcCodes | None:
    """Refusals a real module makes that pymodbus's register flags do not cover.

    The module has no coils or discrete inputs, and none of its registers is writable
    (the read-only flag already refuses holding-register writes; this is the backstop).
    """
    if function_code in BIT_FUNCTION_CODES:
        return ExcCodes.ILLEGAL_FUNCTION
    if values is not None and not is_internal_write(function_code, values):
        return ExcCodes.ILLEGAL_ADDRESS
    return None
