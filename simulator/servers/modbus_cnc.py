"""The simulated CNC's values over Modbus TCP: spindle state to read, macro variables to write.

Real controllers expose this through an option board or a PLC gateway with a
vendor-specific map; the simulator offers one fixed, documented map (MODBUS.md) so
the gateway's compensation loop can be exercised end to end: it reads speed and run
mode, and hands its compensation value over in a retained macro variable (#500–#999),
which the machine applies.

Client writes reach ``MachineLink.write_macro`` inside the request, through the
pymodbus ``SimDevice`` action hook, before the reply is sent: a client that got a
positive reply knows the machine has the value.
"""

from __future__ import annotations

import logging
import math

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.register_codec import float32_to_registers, registers_to_float32_shortest
from simulator.link import MACRO_FIRST, MACRO_LAST, MachineLink, MachineSnapshot
from simulator.servers.modbus_common import (
    BIT_FUNCTION_CODES,
    ModbusEndpoint,
    bit_table_placeholders,
    is_internal_write,
    known_devices_only,
)

log = logging.getLogger(__name__)

#: Holding registers 0–6 (read-only): speeds and probe error float32, run mode uint16.
ACTUAL_SPEED_REGISTER = 0
COMMANDED_SPEED_REGISTER = 2
RUN_MODE_REGISTER = 4
PROBE_ERROR_REGISTER = 5
STATUS_REGISTER_COUNT = 7
#: Macro #n (n = 500…999) is the float32 at registers MACRO_BASE + 2·(n − 500) and +1.
MACRO_BASE = 1000
MACRO_COUNT = MACRO_LAST - MACRO_FIRST + 1
MACRO_REGISTER_COUNT = 2 * MACRO_COUNT


def macro_register(number: int) -> int:
    """First (high-word) register of macro variable #number."""
    if not MACRO_FIRST <= number <= MACRO_LAST:
        raise ValueError(f"macro #{number} is outside #{MACRO_FIRST}–#{MACRO_LAST}")
    return MACRO_BASE + 2 * (number - MACRO_FIRST)


def status_registers(snapshot: MachineSnapshot) -> list[int]:
    """Registers 0–6 for a snapshot: actual and commanded speed, run mode, probe error."""
    probe = math.nan if snapshot.probe_error_um is None else snapshot.probe_error_um
    return [
        *float32_to_registers(snapshot.actual_speed_rpm),
        *float32_to_registers(snapshot.commanded_speed_rpm),
        int(snapshot.run_mode),
        *float32_to_registers(probe),
    ]


class CncModbusServer(ModbusEndpoint):
    """Modbus TCP slave with the CNC's spindle state and its retained macro variables."""

    def __init__(
        self,
        link: MachineLink,
        *,
        host: str = "127.0.0.1",
        port: int,
        device_id: int = 1,
    ) -> None:
        super().__init__()
        if not 1 <= device_id <= 247:
            raise ValueError(f"device id {device_id} is outside the Modbus range 1–247")
        if not 0 <= port <= 65535:
            raise ValueError(f"TCP port {port} is out of range")
        self._link = link
        self._host = host
        self._port = port
        self._device_id = device_id

    @property
    def device_id(self) -> int:
        return self._device_id

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) listened on; the real port once started when port 0 was asked."""
        return self._bound_tcp_address((self._host, self._port))

    def _describe(self) -> str:
        return f"CNC Modbus server on {self._host}:{self._port}"

    def _make_server(self) -> ModbusTcpServer:
        coils, discrete_inputs = bit_table_placeholders()
        holding = [
            SimData(0, count=STATUS_REGISTER_COUNT, values=0, datatype=DataType.REGISTERS),
            # Vacant macros read as NaN until the machine or a client gives them a value.
            SimData(MACRO_BASE, count=MACRO_COUNT, values=math.nan, datatype=DataType.FLOAT32),
        ]
        inputs = [SimData(0, datatype=DataType.REGISTERS)]  # placeholder, refused by the action
        device = SimDevice(
            id=self._device_id,
            simdata=(coils, discrete_inputs, holding, inputs),
            action=self._action,
        )
        return ModbusTcpServer(
            [device],
            address=(self._host, self._port),
            trace_pdu=known_devices_only([self._device_id]),
        )

    async def publish(self) -> None:
        """Copy the link's snapshot into the registers.

        Only macros present in the snapshot are rewritten. The snapshot is taken and
        stored without yielding to the event loop, and a client's write has reached
        the link (``write_macro``) before its registers change, so publish can never
        put back a value older than a write it follows. This relies on the link's
        contract that ``snapshot()`` reflects ``write_macro`` at once.
        """
        server = self._require_server()
        snapshot = self._link.snapshot()
        await server.async_setValues(self._device_id, 3, 0, status_registers(snapshot))
        current = await server.async_getValues(self._device_id, 3, MACRO_BASE, MACRO_REGISTER_COUNT)
        image = [int(register) for register in current]
        for number, value in snapshot.macros.items():
            if MACRO_FIRST <= number <= MACRO_LAST:
                offset = macro_register(number) - MACRO_BASE
                image[offset : offset + 2] = float32_to_registers(value)
        if image != current:
            await server.async_setValues(self._device_id, 3, MACRO_BASE, image)

    async def _action(
        self,
        function_code: int,
        _start_address: int,
        address: int,
        _count: int,
        _registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus calls this on every access, after its own address checks.

        Returning an exception code refuses the request and leaves the registers as
        they were; returning None lets pymodbus store a write.
        """
        if function_code in BIT_FUNCTION_CODES or function_code == 4:
            return ExcCodes.ILLEGAL_FUNCTION  # the map has holding registers only
        if values is None or is_internal_write(function_code, values):
            return None
        return self._apply_client_write(address, [int(v) for v in values])

    def _apply_client_write(self, address: int, values: list[int]) -> ExcCodes | None:
        """Forward a client's macro write to the machine, or say why it is refused."""
        end = address + len(values)
        if address < MACRO_BASE or end > MACRO_BASE + MACRO_REGISTER_COUNT:
            return ExcCodes.ILLEGAL_ADDRESS  # spindle state is read-only
        if (address - MACRO_BASE) % 2 or len(values) % 2:
            return ExcCodes.ILLEGAL_ADDRESS  # half a float32 would corrupt the variable
        writes: list[tuple[int, float]] = []
        for offset in range(0, len(values), 2):
            value = registers_to_float32_shortest(values[offset], values[offset + 1])
            if not math.isfinite(value):
                return ExcCodes.ILLEGAL_VALUE  # never hand NaN/inf to a machine offset
            number = MACRO_FIRST + (address - MACRO_BASE + offset) // 2
            writes.append((number, value))
        for number, value in writes:
            try:
                self._link.write_macro(number, value)
            except ValueError as exc:
                log.warning("machine refused macro #%d = %r: %s", number, value, exc)
                return ExcCodes.ILLEGAL_VALUE
        return None
