"""The simulated CNC's values over Modbus TCP: spindle state to read, macro variables to write.

Real controllers expose this through an option board or a PLC gateway with a
vendor-specific map; the simulator serves a register map (by default
``drivers/maps/sim_cnc.yaml``, documented in MODBUS.md; any byte or word order) so
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
from functools import cache

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.register_map import DeviceRegisters
from drivers.schema import CNC_MAP, load_register_map
from simulator.link import MACRO_FIRST, MACRO_LAST, MachineLink, MachineSnapshot
from simulator.servers.modbus_common import (
    BIT_FUNCTION_CODES,
    ModbusEndpoint,
    bit_table_placeholders,
    is_internal_write,
    known_devices_only,
)

log = logging.getLogger(__name__)

#: The shipped map's layout (drivers/maps/sim_cnc.yaml): holding registers 0–6 (read-only)
#: hold speeds and probe error as float32 and the run mode as uint16; macro #n
#: (n = 500…999) is the float32 at registers MACRO_BASE + 2·(n − 500) and +1.
ACTUAL_SPEED_REGISTER = 0
COMMANDED_SPEED_REGISTER = 2
RUN_MODE_REGISTER = 4
PROBE_ERROR_REGISTER = 5
STATUS_REGISTER_COUNT = 7
MACRO_BASE = 1000
MACRO_COUNT = MACRO_LAST - MACRO_FIRST + 1
MACRO_REGISTER_COUNT = 2 * MACRO_COUNT


@cache
def sim_cnc_layout() -> DeviceRegisters:
    """The shipped simulated-CNC map, ready for the wire."""
    return DeviceRegisters(load_register_map(CNC_MAP))


def macro_register(number: int) -> int:
    """First (high-word) register of macro variable #number in the shipped map."""
    if not MACRO_FIRST <= number <= MACRO_LAST:
        raise ValueError(f"macro #{number} is outside #{MACRO_FIRST}–#{MACRO_LAST}")
    macros = sim_cnc_layout().macros
    assert macros is not None
    return macros.register(number)


def status_values(snapshot: MachineSnapshot) -> dict[str, float]:
    """The values of the map's spindle-state fields for a snapshot (engineering units)."""
    probe = math.nan if snapshot.probe_error_um is None else snapshot.probe_error_um
    return {
        "actual_speed_rpm": snapshot.actual_speed_rpm,
        "commanded_speed_rpm": snapshot.commanded_speed_rpm,
        "run_mode": int(snapshot.run_mode),
        "probe_error_um": probe,
    }


class CncModbusServer(ModbusEndpoint):
    """Modbus TCP slave with the CNC's spindle state and its retained macro variables."""

    def __init__(
        self,
        link: MachineLink,
        *,
        host: str = "127.0.0.1",
        port: int,
        device_id: int = 1,
        registers: DeviceRegisters | None = None,
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
        self._layout = registers if registers is not None else sim_cnc_layout()
        if self._layout.macros is None:
            raise ValueError(f"register map {self._layout.map.label} has no macro block")
        self._macros = self._layout.macros
        self._blocks = [b for b in self._layout.blocks() if b[0] == "holding"]
        # Per macro, the snapshot's value object last encoded and its registers: the
        # machine keeps a macro's float object until it changes, so most of the 500
        # macros of a publish are found here by identity and not encoded again.
        self._encoded: dict[int, tuple[float, list[int]]] = {}

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
            SimData(
                start, count=sum(c.width for c in members), values=0, datatype=DataType.REGISTERS
            )
            for _, start, members in self._blocks
        ]
        # Vacant macros read as NaN until the machine or a client gives them a value.
        macros = self._macros
        vacant = macros.encode(math.nan) * (macros.last - macros.first + 1)
        holding.append(SimData(macros.address, values=vacant, datatype=DataType.REGISTERS))
        holding.sort(key=lambda block: block.address)
        inputs = [SimData(0, datatype=DataType.REGISTERS)]  # placeholder, refused by the action
        device = SimDevice(
            id=self._device_id,
            simdata=(coils, discrete_inputs, holding, inputs),
            action=self._action,
        )
        return ModbusTcpServer(
            [device],
            address=(self._host, self._port),
            trace_pdu=known_devices_only([self._device_id], received=self.received),
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
        values = status_values(snapshot)
        raws = {
            name: codec.raw(values[name])[0]
            for name, codec in self._layout.fields.items()
            if name in values
        }
        for _, start, members in self._blocks:
            registers = self._layout.encode_block(members, raws)
            await server.async_setValues(self._device_id, 3, start, registers)
        macros = self._macros
        count = macros.end - macros.address
        current = await server.async_getValues(self._device_id, 3, macros.address, count)
        image = [int(register) for register in current]
        encoded = self._encoded
        for number, value in snapshot.macros.items():
            if macros.first <= number <= macros.last:
                known = encoded.get(number)
                if known is None or known[0] is not value:
                    known = encoded[number] = (value, macros.encode(value))
                offset = macros.register(number) - macros.address
                image[offset : offset + macros.width] = known[1]
        if image != current:
            await server.async_setValues(self._device_id, 3, macros.address, image)

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
        macros = self._macros
        end = address + len(values)
        if address < macros.address or end > macros.end:
            return ExcCodes.ILLEGAL_ADDRESS  # spindle state is read-only
        if (address - macros.address) % macros.width or len(values) % macros.width:
            return ExcCodes.ILLEGAL_ADDRESS  # half a value would corrupt the variable
        writes: list[tuple[int, float]] = []
        for offset in range(0, len(values), macros.width):
            value = macros.decode(values[offset : offset + macros.width])
            if not math.isfinite(value):
                return ExcCodes.ILLEGAL_VALUE  # never hand NaN/inf to a machine offset
            writes.append((macros.number(address + offset), value))
        for number, value in writes:
            try:
                self._link.write_macro(number, value)
            except ValueError as exc:
                log.warning("machine refused macro #%d = %r: %s", number, value, exc)
                return ExcCodes.ILLEGAL_VALUE
        return None
