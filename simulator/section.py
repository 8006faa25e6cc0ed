"""The ``simulator`` section of ``config.yaml``: the schema, and everything it must agree with.

Checked by the same loader and validator as the gateway's own sections
(:mod:`drivers.yaml_loader`), so a bad key is refused with its line. The
machine overrides (``machine:``) are merged into ``simulator/machine.yaml`` and
checked against its schema here, the programme and the hidden effects are
looked up, and every endpoint needs its own port: whatever ``simulate`` would
refuse only when it starts serving is refused when the file is loaded.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from drivers.yaml_loader import KeyPathError, first_problem
from simulator.effects import parse_effects
from simulator.machine import AMBIENT_CHANNEL
from simulator.params import merged_params
from simulator.programs import program_by_name


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class DeviceConfig(Strict):
    device_id: int = Field(ge=1, le=247)
    channels: list[str | None] = Field(min_length=1, max_length=8)


class RtuBusConfig(Strict):
    port: str
    baudrate: int = 19200
    parity: Literal["N", "E", "O"] = "N"
    devices: list[DeviceConfig] = Field(min_length=1)


class TcpBusConfig(Strict):
    host: str = "127.0.0.1"
    port: int = Field(ge=1, le=65535)
    devices: list[DeviceConfig] = Field(min_length=1)


class TransmittersConfig(Strict):
    rtu: RtuBusConfig | None = None
    tcp: TcpBusConfig | None = None


class EndpointConfig(Strict):
    host: str = "127.0.0.1"
    port: int = Field(ge=1, le=65535)


class CncConfig(Strict):
    opcua: EndpointConfig | None = None
    modbus: EndpointConfig | None = None


class SimulatorConfig(Strict):
    program: str = "iso230-spectrum"
    effects: list[str] = Field(default_factory=list)
    seed: int = 0
    speedup: float = Field(default=60.0, gt=0)
    publish_period_s: float = Field(default=0.2, gt=0)
    machine: dict[str, Any] = Field(default_factory=dict)
    transmitters: TransmittersConfig = TransmittersConfig()
    cnc: CncConfig = CncConfig()

    @field_validator("program")
    @classmethod
    def _known_program(cls, value: str) -> str:
        program_by_name(value)
        return value

    @field_validator("effects")
    @classmethod
    def _known_effects(cls, value: list[str]) -> list[str]:
        parse_effects(value)
        return value

    @field_validator("machine")
    @classmethod
    def _machine_params(cls, value: dict[str, Any]) -> dict[str, Any]:
        try:
            merged_params(value)
        except ValidationError as exc:
            loc, message = first_problem(exc)
            raise KeyPathError(loc, message) from None
        return value

    @model_validator(mode="after")
    def _endpoints(self) -> SimulatorConfig:
        """Every channel names a sensor of the machine; no two servers share a port."""
        sensors = {*merged_params(self.machine).sensors, AMBIENT_CHANNEL}
        bound: dict[tuple[str, int], tuple[str, ...]] = {}
        buses = {"rtu": self.transmitters.rtu, "tcp": self.transmitters.tcp}
        for bus_name, bus in buses.items():
            if bus is None:
                continue
            for d, device in enumerate(bus.devices):
                for c, channel in enumerate(device.channels):
                    if channel is not None and channel not in sensors:
                        raise KeyPathError(
                            ("transmitters", bus_name, "devices", d, "channels", c),
                            f"the simulated machine has no sensor '{channel}' "
                            f"(it has {', '.join(sorted(sensors))})",
                        )
        servers: dict[tuple[str, ...], TcpBusConfig | EndpointConfig | None] = {
            ("transmitters", "tcp"): self.transmitters.tcp,
            ("cnc", "opcua"): self.cnc.opcua,
            ("cnc", "modbus"): self.cnc.modbus,
        }
        for key, server in servers.items():
            if server is None:
                continue
            address = (server.host, server.port)
            if address in bound:
                raise KeyPathError(
                    (*key, "port"),
                    f"{server.host}:{server.port} is already served by "
                    f"{'.'.join(bound[address])}; each server needs its own port",
                )
            bound[address] = key
        return self
