"""One pydantic model per field-bus concept, shared by the gateway's config and the simulator's.

A serial port (with its parity), a TCP endpoint, a Modbus device, the bus that
carries devices, and a device's register map are declared here once; the
gateway's ``config.yaml`` (:mod:`gateway.config`) and the simulator's section of
it (:mod:`simulator.serve`) build on these, so a key means the same thing in
both and is checked by the same code.

A register map is data, in the manner of Telegraf's ``inputs.modbus``: every
field names its address, register type, data type, byte and word order, scale
and offset; a map may declare a fault-code convention (status codes and value
codes that are never a reading) and Telegraf-style ``workarounds`` for a
device's quirks. Maps ship as YAML files in ``drivers/maps/`` (named by their
stem, e.g. ``pt100_8ch``); a device entry may also name a file path (relative to
the file that names it) or give the map inline.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from drivers.yaml_loader import KeyPathError, ReferencedFileError, YamlError, load_yaml, validate

MAPS_DIR = Path(__file__).with_name("maps")
"""The register maps that ship with the package (``<name>.yaml``)."""
TRANSMITTER_MAP = "pt100_8ch"
"""The map of a transmitter device that names none: the 8-channel 0.1 °C Pt100 module."""
CNC_MAP = "sim_cnc"
"""The map of the simulated CNC's Modbus TCP interface."""
MAX_REGISTERS_PER_REQUEST = 125
"""The Modbus limit of one read (FC3/FC4): 125 registers in a 256-byte frame."""

DataType = Literal["int16", "uint16", "int32", "uint32", "float32", "int64", "uint64", "float64"]
RegisterType = Literal["holding", "input"]
Order = Literal["big", "little"]

#: Registers each data type takes.
WIDTH: dict[str, int] = {
    "int16": 1,
    "uint16": 1,
    "int32": 2,
    "uint32": 2,
    "float32": 2,
    "int64": 4,
    "uint64": 4,
    "float64": 4,
}


def integer_range(data_type: str) -> tuple[int, int] | None:
    """(smallest, largest) value of an integer data type; None for a float type."""
    if data_type.startswith("float"):
        return None
    bits = 16 * WIDTH[data_type]
    if data_type.startswith("u"):
        return 0, 2**bits - 1
    return -(2 ** (bits - 1)), 2 ** (bits - 1) - 1


class Strict(BaseModel):
    """The base of every schema the project reads: unknown keys, NaN and inf are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# -- ports and endpoints ---------------------------------------------------------------


class RtuPort(Strict):
    """A serial (RS-485) port: 8 data bits and 1 stop bit, parity none, even or odd."""

    port: str
    baudrate: int = Field(default=19200, gt=0)
    parity: Literal["N", "E", "O"] = "N"
    #: Pause between frames when a device needs more than the RTU t3.5 (the longer wins).
    min_silence_s: float = Field(default=0.0, ge=0, le=1.0)


class TcpEndpoint(Strict):
    """A TCP host and port (a Modbus TCP device or gateway, an OPC UA server)."""

    host: str = "127.0.0.1"
    port: int = Field(ge=1, le=65535)


# -- register maps ---------------------------------------------------------------------


class Workarounds(Strict):
    """Telegraf's ``workarounds`` for real devices' quirks.

    - ``pause_between_requests_s``: the device needs this long after one request
      ends before it takes the next (slow converters, some RS-485 repeaters).
    - ``max_registers_per_request``: the device refuses longer reads than this
      (1…125; 125 is the protocol's own limit).
    - ``one_request_per_field``: the device refuses a read spanning two fields.
    """

    pause_between_requests_s: float = Field(default=0.0, ge=0, le=10)
    max_registers_per_request: int = Field(default=MAX_REGISTERS_PER_REQUEST, ge=1, le=125)
    one_request_per_field: bool = False


class FaultConvention(Strict):
    """How a device tells a fault from a reading.

    ``status_codes``: the meaning of each status-register value (``ok`` is the
    one good code; the others are named faults, e.g. ``open_circuit: 1``).
    ``value_codes``: raw values (before scale and offset) the value register
    shows for a fault (e.g. the Pt100 module's ``open_circuit: 32767``); such a
    value is never a reading, even next to an OK status, because a clamped
    reading has the same counts and only the status tells them apart.
    """

    status_codes: dict[str, int] = Field(default_factory=lambda: {"ok": 0})
    value_codes: dict[str, float] = Field(default_factory=dict)

    @field_validator("status_codes")
    @classmethod
    def _has_ok(cls, codes: dict[str, int]) -> dict[str, int]:
        if "ok" not in codes:
            raise ValueError("needs the code of a good reading, 'ok' (e.g. ok: 0)")
        if len(set(codes.values())) != len(codes):
            raise ValueError(f"two meanings share one code: {codes}")
        return codes


class RegisterField(Strict):
    """One value in a device's registers.

    ``value = raw · scale + offset``, where ``raw`` is the ``data_type`` decoded
    from its registers in ``byte_order`` (within a register) and ``word_order``
    (of the registers of a 32/64-bit value). ``register_type``, ``byte_order`` and
    ``word_order`` default to the map's. ``status`` names another field of the
    map that holds this one's status under the map's ``faults`` convention.
    """

    name: str = Field(min_length=1)
    address: int = Field(ge=0, le=65535)
    data_type: DataType
    register_type: RegisterType | None = None
    byte_order: Order | None = None
    word_order: Order | None = None
    scale: float = 1.0
    offset: float = 0.0
    status: str | None = None

    @field_validator("scale")
    @classmethod
    def _nonzero(cls, scale: float) -> float:
        if scale == 0:
            raise ValueError("0 would make every reading 0; a non-zero factor was expected")
        return scale

    @property
    def width(self) -> int:
        return WIDTH[self.data_type]

    @model_validator(mode="after")
    def _fits(self) -> RegisterField:
        if self.address + self.width > 65536:
            raise KeyPathError(
                ("address",),
                f"{self.data_type} at {self.address} ends beyond register 65535",
            )
        return self


def first_places(values: list[Any], items: str, key: str, rule: str) -> dict[Any, int]:
    """Where each value first stands in ``values``; a repeat is refused at its place
    (``items[i].key``), naming the first one and the ``rule``."""
    places: dict[Any, int] = {}
    for index, value in enumerate(values):
        if value in places:
            shown = f"'{value}'" if isinstance(value, str) else str(value)
            raise KeyPathError(
                (items, index, key), f"{shown} is already {items}[{places[value]}]; {rule}"
            )
        places[value] = index
    return places


class MacroBlock(Strict):
    """A CNC's macro variables #first…#last, one ``data_type`` value each from ``address``."""

    first: int = Field(default=500, ge=0)
    last: int = Field(default=999, ge=0)
    address: int = Field(ge=0, le=65535)
    data_type: DataType = "float32"
    byte_order: Order | None = None
    word_order: Order | None = None

    @model_validator(mode="after")
    def _fits(self) -> MacroBlock:
        if self.last < self.first:
            raise KeyPathError(("last",), f"#{self.last} is below first (#{self.first})")
        if self.end > 65536:
            raise KeyPathError(("address",), f"macros #{self.first}…#{self.last} end beyond 65535")
        return self

    @property
    def width(self) -> int:
        return WIDTH[self.data_type]

    @property
    def end(self) -> int:
        """One past the last register of the block."""
        return self.address + self.width * (self.last - self.first + 1)


class RegisterMap(Strict):
    """A device's registers, as data.

    ``fields`` are read every cycle, grouped into one request per contiguous
    block of one register type (split at ``workarounds.max_registers_per_request``).
    ``channels`` lists, in channel order, the fields a device entry's
    ``channels: [T1, T2, …]`` wires sensors to. ``macros`` is the writable block
    of a CNC map (holding registers).
    """

    name: str | None = None
    description: str = ""
    register_type: RegisterType = "holding"
    byte_order: Order = "big"
    word_order: Order = "big"
    fields: list[RegisterField] = Field(min_length=1)
    channels: list[str] = Field(default_factory=list)
    faults: FaultConvention | None = None
    macros: MacroBlock | None = None
    workarounds: Workarounds = Workarounds()

    @model_validator(mode="after")
    def _consistent(self) -> RegisterMap:
        names = first_places([item.name for item in self.fields], "fields", "name", "one name each")
        self._check_overlaps()
        for index, item in enumerate(self.fields):
            if item.status is not None:
                if item.status not in names or item.status == item.name:
                    raise KeyPathError(
                        ("fields", index, "status"),
                        f"no other field named '{item.status}' in this map",
                    )
                if self.faults is None:
                    raise KeyPathError(
                        ("fields", index, "status"),
                        "a status field needs the map's 'faults' convention (status_codes)",
                    )
        for index, channel in enumerate(self.channels):
            if channel not in names:
                raise KeyPathError(("channels", index), f"no field named '{channel}' in this map")
            if channel in self.channels[:index]:
                raise KeyPathError(("channels", index), f"'{channel}' is already a channel")
        limit = self.workarounds.max_registers_per_request
        for index, item in enumerate(self.fields):
            if item.width > limit:
                raise KeyPathError(
                    ("fields", index, "data_type"),
                    f"{item.data_type} takes {item.width} registers, more than "
                    f"workarounds.max_registers_per_request ({limit})",
                )
        return self

    def _check_overlaps(self) -> None:
        """No register belongs to two fields (or to a field and the macro block)."""
        owner: dict[tuple[str, int], str] = {}
        if self.macros is not None:
            for register in range(self.macros.address, self.macros.end):
                owner["holding", register] = "the macro block"
        for index, item in enumerate(self.fields):
            kind = self.kind_of(item)
            for register in range(item.address, item.address + item.width):
                other = owner.get((kind, register))
                if other is not None:
                    raise KeyPathError(
                        ("fields", index, "address"),
                        f"{kind} register {register} is already {other}; fields must not overlap",
                    )
            for register in range(item.address, item.address + item.width):
                owner[kind, register] = f"field '{item.name}'"

    def kind_of(self, item: RegisterField) -> str:
        """The register type of a field (its own, or the map's)."""
        return item.register_type or self.register_type

    def field(self, name: str) -> RegisterField:
        for item in self.fields:
            if item.name == name:
                return item
        raise KeyError(f"register map {self.label}: no field '{name}'")

    @property
    def label(self) -> str:
        return f"'{self.name}'" if self.name else "(inline)"


def shipped_maps() -> list[str]:
    """Names of the register maps in ``drivers/maps/``."""
    return sorted(path.stem for path in MAPS_DIR.glob("*.yaml"))


@cache
def _load_map_file(path: Path) -> RegisterMap:
    document = load_yaml(path)
    if not isinstance(document.data, dict):
        raise YamlError(f"{path}:1: a register map (a mapping with 'fields') was expected")
    register_map = validate(document, RegisterMap)
    if register_map.name is None:
        register_map = register_map.model_copy(update={"name": path.stem})
    return register_map


def load_register_map(source: str, base_dir: Path | None = None) -> RegisterMap:
    """The map named ``source``: a shipped map's name, or a YAML file (relative to ``base_dir``).

    A problem inside the file is a :class:`YamlError` naming that file, line and key.
    """
    if "/" not in source and not source.endswith((".yaml", ".yml")):
        path = MAPS_DIR / f"{source}.yaml"
        if not path.is_file():
            raise ValueError(
                f"no register map '{source}' ships with the gateway (shipped: "
                f"{', '.join(shipped_maps())}); give a file path for your own"
            )
    else:
        path = Path(source)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        if path.is_dir():
            raise ValueError(f"register map file {path} is a folder; a YAML file was expected")
        if not path.is_file():
            raise ValueError(f"register map file {path} does not exist")
    return _load_map_file(path)


def map_from_source(cls: type, value: Any, info: ValidationInfo) -> Any:
    """A ``map:`` key's value: a name or path is loaded, a mapping is validated in place."""
    if not isinstance(value, str):
        return value
    base_dir = (info.context or {}).get("source_dir")
    try:
        return load_register_map(value, base_dir)
    except YamlError as exc:
        raise ReferencedFileError(exc) from None


# -- devices and buses -----------------------------------------------------------------


class Device(Strict):
    """A Modbus device on a bus: its id, its register map, and the sensor on each channel.

    ``channels[i]`` is the sensor on the map's channel i+1; ``null`` (or a missing
    trailing entry) is a channel without a probe. ``map`` is a shipped map's
    name, a file, or the map inline; ``workarounds`` replaces the map's.
    """

    device_id: int = Field(ge=1, le=247)
    channels: list[str | None] = Field(min_length=1)
    map: RegisterMap = Field(default_factory=lambda: load_register_map(TRANSMITTER_MAP))
    workarounds: Workarounds | None = None

    _load_map = field_validator("map", mode="before")(map_from_source)

    @model_validator(mode="after")
    def _channels_fit_map(self) -> Device:
        available = len(self.map.channels)
        if len(self.channels) > available:
            raise KeyPathError(
                ("channels",),
                f"{len(self.channels)} channels, the register map {self.map.label} has {available}",
            )
        return self

    @property
    def effective_workarounds(self) -> Workarounds:
        return self.workarounds if self.workarounds is not None else self.map.workarounds


class Devices(Strict):
    """The devices on one bus: at least one."""

    devices: list[Device] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique_ids(self) -> Devices:
        ids = [device.device_id for device in self.devices]
        first_places(ids, "devices", "device_id", "one id per device on a bus")
        return self


class Bus(Devices):
    """A client's bus: an RS-485 line (``rtu``) or a Modbus TCP port (``tcp``), and its devices."""

    name: str
    rtu: RtuPort | None = None
    tcp: TcpEndpoint | None = None
    timeout_s: float = Field(default=0.3, gt=0)

    @model_validator(mode="after")
    def _one_transport(self) -> Bus:
        if (self.rtu is None) == (self.tcp is None):
            raise ValueError("give exactly one of 'rtu' or 'tcp'")
        return self


class RtuBus(RtuPort, Devices):
    """A served RS-485 bus: the port and the devices behind it (the simulator's form)."""


class TcpBus(TcpEndpoint, Devices):
    """A served Modbus TCP port and the devices behind it (the simulator's form)."""


# -- the CNC over Modbus -----------------------------------------------------------------

CNC_FIELDS = ("actual_speed_rpm", "commanded_speed_rpm")
"""Fields a CNC's register map must have; ``run_mode`` and ``probe_error_um`` are optional."""


def cnc_map(
    speed_register: int = 0,
    commanded_register: int = 2,
    run_mode_register: int | None = 4,
    macro_base_register: int = 1000,
    macro_first: int = 500,
    macro_last: int | None = None,
) -> RegisterMap:
    """The CNC map of the ``*_register`` keys: float32 speeds, uint16 run mode, big/big.

    What a Modbus CNC entry without ``map`` has always meant (``sim_cnc`` with
    other addresses), so those entries keep working. Without ``macro_last`` the
    macros run on as far as the registers go (the CNC refuses what it lacks).
    """
    if macro_last is None:
        macro_last = macro_first + (65536 - macro_base_register) // 2 - 1
    fields = [
        RegisterField(name="actual_speed_rpm", address=speed_register, data_type="float32"),
        RegisterField(name="commanded_speed_rpm", address=commanded_register, data_type="float32"),
    ]
    if run_mode_register is not None:
        fields.append(RegisterField(name="run_mode", address=run_mode_register, data_type="uint16"))
    return RegisterMap(
        name="cnc registers",
        fields=fields,
        macros=MacroBlock(first=macro_first, last=macro_last, address=macro_base_register),
    )


def check_cnc_map(register_map: RegisterMap) -> None:
    """Refuse, at the ``map`` key, a map a CNC driver or server cannot use."""
    names = {item.name for item in register_map.fields}
    missing = [name for name in CNC_FIELDS if name not in names]
    if missing:
        raise KeyPathError(
            ("map", "fields"),
            f"a CNC's register map needs the fields {list(CNC_FIELDS)}; missing {missing}",
        )
    if register_map.macros is None:
        raise KeyPathError(("map",), "a CNC's register map needs its 'macros' block")
    for name in CNC_FIELDS:
        if register_map.kind_of(register_map.field(name)) != "holding":
            raise KeyPathError(("map", "fields"), f"'{name}' must be a holding register")


class ModbusServerEndpoint(TcpEndpoint):
    """A served Modbus TCP device with one register map (the simulated CNC)."""

    device_id: int = Field(default=1, ge=1, le=247)
    map: RegisterMap = Field(default_factory=lambda: load_register_map(CNC_MAP))

    _load_map = field_validator("map", mode="before")(map_from_source)

    @model_validator(mode="after")
    def _usable_map(self) -> ModbusServerEndpoint:
        check_cnc_map(self.map)
        return self
