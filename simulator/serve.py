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

from drivers.clock import AcceleratedClock, Clock
from drivers.servers.modbus_cnc import CncModbusServer
from drivers.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from drivers.servers.opcua_cnc import CncOpcUaServer
from drivers.yaml_loader import YamlError, load_yaml, validate
from simulator.effects import parse_effects
from simulator.machine import SimulatedMachine
from simulator.params import load_params
from simulator.programs import program_by_name
from simulator.section import (
    CncConfig,
    DeviceConfig,
    EndpointConfig,
    RtuBusConfig,
    SimulatorConfig,
    TcpBusConfig,
    TransmittersConfig,
)

__all__ = [
    "CncConfig",
    "DeviceConfig",
    "EndpointConfig",
    "SimulatedPlant",
    "SimulatorConfig",
    "TransmittersConfig",
    "load_simulator_config",
]


def load_simulator_config(path: Path) -> SimulatorConfig:
    """The ``simulator`` section of a config file, validated (errors name the line and key)."""
    document = load_yaml(path)
    if not isinstance(document.data, dict) or document.data.get("simulator") is None:
        raise YamlError(f"{path}:1: no 'simulator' section to serve")
    return validate(document, SimulatorConfig, ("simulator",))


class SimulatedPlant:
    """The machine and its endpoints, run together on one clock."""

    def __init__(self, config: SimulatorConfig, clock: Clock | None = None) -> None:
        self.config = config
        self.clock = clock or AcceleratedClock(config.speedup)
        params = load_params(config.machine, source="simulator.machine")
        self.machine = SimulatedMachine(
            params,
            program_by_name(config.program),
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

        def devices(bus: RtuBusConfig | TcpBusConfig) -> list[TransmitterDevice]:
            return [TransmitterDevice(d.device_id, list(d.channels)) for d in bus.devices]

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
                machine, host=modbus.host, port=modbus.port
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

    async def serve_forever(self) -> None:
        async with self:
            await asyncio.Event().wait()
