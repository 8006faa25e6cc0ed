"""Serving the simulated machine over its protocols, as ``config.yaml`` describes.

One machine per config: temperature transmitters on a Modbus RTU bus (a serial
port, e.g. one end of a ``socat`` pty pair) and/or Modbus TCP, and the CNC over
OPC UA and/or Modbus TCP. A single loop advances the machine to the clock's
time and republishes every endpoint; client writes of macro variables reach
the machine as they arrive, so the compensation closes the loop.
"""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, field_validator, model_validator

from drivers.clock import AcceleratedClock, Clock
from drivers.register_map import DeviceRegisters
from drivers.schema import ModbusServerEndpoint, RtuBus, Strict, TcpBus, TcpEndpoint
from drivers.yaml_loader import KeyPathError, YamlError, first_problem, load_yaml, validate
from simulator.effects import parse_effects
from simulator.machine import AMBIENT_CHANNEL, SimulatedMachine
from simulator.params import Ageing, deep_merge, load_params, merged_params
from simulator.programs import SpeedProgram, program_by_name
from simulator.servers.modbus_cnc import CncModbusServer
from simulator.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from simulator.servers.opcua_cnc import CncOpcUaServer


class TransmittersConfig(Strict):
    """The simulated transmitter modules: an RS-485 bus and/or a Modbus TCP port."""

    rtu: RtuBus | None = None
    tcp: TcpBus | None = None


class CncConfig(Strict):
    """The simulated CNC's servers; ``modbus`` may name the register map it serves."""

    opcua: TcpEndpoint | None = None
    modbus: ModbusServerEndpoint | None = None


class ProbeSettings(Strict):
    """The probe cycle on the CNC: how often (machine seconds) and how noisy (µm, 1 σ)."""

    period_s: float | None = Field(default=None, gt=0)
    noise_um: float | None = Field(default=None, ge=0)


class SimulatorConfig(Strict):
    """The ``simulator`` section; what serving would refuse later is refused here, located.

    The programme and the hidden effects must exist, the machine overrides must
    fit ``simulator/machine.yaml``'s schema once merged, every channel must name
    a sensor of the machine, and no two servers may share a host and port.
    ``probe`` (period_s: machine seconds between probes, noise_um: 1 σ) and
    ``ageing`` (see :class:`simulator.params.Ageing`) are shorthands for the same
    keys under ``machine``, and win over them.
    """

    program: str = "iso230-spectrum"
    #: machine seconds at rest, the spindle stopped, before the programme starts: a thermal
    #: test zeroes its probe and takes its temperature reference on the cold machine at rest
    rest_before_s: float = Field(default=0.0, ge=0, allow_inf_nan=False)
    effects: list[str] = Field(default_factory=list)
    seed: int = 0
    speedup: float = Field(default=60.0, gt=0)
    publish_period_s: float = Field(default=0.2, gt=0)
    machine: dict[str, Any] = Field(default_factory=dict)
    probe: ProbeSettings = ProbeSettings()
    ageing: Ageing | None = None
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

    def with_probe(
        self, period_s: float | None = None, noise_um: float | None = None
    ) -> SimulatorConfig:
        """This config with the probe period and/or noise replaced (the CLI's options)."""
        probe = self.probe.model_dump(exclude_none=True)
        probe.update(
            {k: v for k, v in (("period_s", period_s), ("noise_um", noise_um)) if v is not None}
        )
        return SimulatorConfig.model_validate({**self.model_dump(), "probe": probe})

    @property
    def machine_overrides(self) -> dict[str, Any]:
        """``machine`` with ``probe`` and ``ageing`` merged in (those two win)."""
        extra: dict[str, Any] = {}
        probe = self.probe.model_dump(exclude_none=True)
        if probe:
            extra["probe"] = probe
        if self.ageing is not None:
            extra["ageing"] = self.ageing.model_dump()
        return deep_merge(self.machine, extra)

    @model_validator(mode="after")
    def _endpoints(self) -> SimulatorConfig:
        """Every channel names a sensor of the machine; no two servers share a port."""
        sensors = {*merged_params(self.machine_overrides).sensors, AMBIENT_CHANNEL}
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
        servers: dict[tuple[str, ...], TcpEndpoint | None] = {
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


def load_simulator_config(path: Path) -> SimulatorConfig:
    """The ``simulator`` section of a config file, validated (errors name the line and key)."""
    document = load_yaml(path)
    if not isinstance(document.data, dict) or document.data.get("simulator") is None:
        raise YamlError(f"{path}:1: no 'simulator' section to serve")
    return validate(document, SimulatorConfig, ("simulator",))


def with_rest_before(program: SpeedProgram, rest_s: float) -> SpeedProgram:
    """``program`` opened by ``rest_s`` machine seconds at 0 r/min (unchanged for 0)."""
    if rest_s <= 0:
        return program
    return SpeedProgram(program.name, ((rest_s, 0.0), *program.segments))


class SimulatedPlant:
    """The machine and its endpoints, run together on one clock."""

    def __init__(self, config: SimulatorConfig, clock: Clock | None = None) -> None:
        self.config = config
        self.clock = clock or AcceleratedClock(config.speedup)
        params = load_params(config.machine_overrides, source="simulator.machine")
        self.machine = SimulatedMachine(
            params,
            with_rest_before(program_by_name(config.program), config.rest_before_s),
            parse_effects(config.effects),
            seed=config.seed,
            start_s=self.clock.now(),
        )
        self._factories = self._endpoint_factories(config)
        self.rtu_transmitters = self._make("rtu_transmitters")
        self.tcp_transmitters = self._make("tcp_transmitters")
        self.cnc_opcua = self._make("cnc_opcua")
        self.cnc_modbus = self._make("cnc_modbus")
        self._task: asyncio.Task[None] | None = None

    def _endpoint_factories(self, config: SimulatorConfig) -> dict[str, Any]:
        buses, cnc, machine = config.transmitters, config.cnc, self.machine

        def devices(bus: RtuBus | TcpBus) -> list[TransmitterDevice]:
            return [
                TransmitterDevice(
                    d.device_id,
                    list(d.channels),
                    DeviceRegisters(d.map, d.effective_workarounds),
                )
                for d in bus.devices
            ]

        factories: dict[str, Any] = {}
        if buses.rtu is not None:
            rtu = buses.rtu
            factories["rtu_transmitters"] = lambda: TransmitterServer(
                machine,
                devices(rtu),
                serial_port=rtu.port,
                baudrate=rtu.baudrate,
                parity=rtu.parity,
            )
        if buses.tcp is not None:
            tcp = buses.tcp
            factories["tcp_transmitters"] = lambda: TransmitterServer(
                machine, devices(tcp), tcp=(tcp.host, tcp.port)
            )
        if cnc.opcua is not None:
            opcua = cnc.opcua
            factories["cnc_opcua"] = lambda: CncOpcUaServer(
                machine, host=opcua.host, port=opcua.port
            )
        if cnc.modbus is not None:
            modbus = cnc.modbus
            factories["cnc_modbus"] = lambda: CncModbusServer(
                machine,
                host=modbus.host,
                port=modbus.port,
                device_id=modbus.device_id,
                registers=DeviceRegisters(modbus.map),
            )
        return factories

    def _make(self, name: str) -> Any:
        factory = self._factories.get(name)
        return None if factory is None else factory()

    async def take_down(self, name: str) -> None:
        """Stop one endpoint (``cnc_opcua``, ``cnc_modbus``, …): a server or link outage."""
        endpoint = getattr(self, name)
        if endpoint is not None:
            setattr(self, name, None)
            await endpoint.stop()

    async def bring_up(self, name: str) -> None:
        """Start a fresh server for an endpoint that was taken down (a restart)."""
        if getattr(self, name) is None and name in self._factories:
            endpoint = self._make(name)
            await endpoint.start()
            setattr(self, name, endpoint)

    @property
    def endpoints(self) -> list[Any]:
        """The configured endpoints, transmitters first."""
        candidates = (self.rtu_transmitters, self.tcp_transmitters, self.cnc_opcua, self.cnc_modbus)
        return [endpoint for endpoint in candidates if endpoint is not None]

    async def start(self) -> None:
        for endpoint in self.endpoints:
            await endpoint.start()
        await self.update()
        self._task = asyncio.create_task(self._run())

    async def update(self) -> None:
        """Advance the machine to now and republish every endpoint."""
        self.machine.advance_to(self.clock.now())
        for endpoint in self.endpoints:
            await endpoint.publish()

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(self.config.publish_period_s)
            await self.update()

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        for endpoint in reversed(self.endpoints):
            await endpoint.stop()

    async def __aenter__(self) -> SimulatedPlant:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def serve_until(self, stop: asyncio.Event) -> None:
        """Serve until ``stop`` is set, then close every endpoint."""
        async with self:
            await stop.wait()
