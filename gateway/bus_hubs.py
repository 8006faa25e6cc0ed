"""Which transmitter buses of the configuration are one physical RS-485 line.

A line is named by its serial port path: every bus section (of any machine)
that gives the same ``rtu.port`` is on that line and reads through one
:class:`drivers.bus_hub.BusHub`. No new key is needed, but the sections must
agree: one line has one baud rate and one parity, and one device id answers on
it once (two sections naming the same id would read the same module, or two
modules would answer one request and garble each other's replies). Those are
refused by :func:`check_shared_lines`, located on the second section.

What may differ is taken at its most patient: the line's request timeout is the
longest any of its sections asks, the inter-frame silence the longest of the
RTU t3.5 at the line's baud rate and every ``rtu.min_silence_s``.

Modbus TCP buses keep one connection each: a TCP server carries concurrent
connections and tells replies apart by transaction id, so nothing collides.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from drivers.bus_hub import BusHub, rtu_silence_s
from drivers.transmitters import ModbusConnection
from drivers.yaml_loader import KeyPathError, format_path

if TYPE_CHECKING:
    from gateway.config import BusSection, MachineSection

Where = tuple[str | int, ...]


def _rtu_buses(machines: Sequence[MachineSection]) -> dict[str, list[tuple[Where, BusSection]]]:
    """Bus sections by serial port path, each with its key path in the configuration."""
    lines: dict[str, list[tuple[Where, BusSection]]] = {}
    for m, machine in enumerate(machines):
        for b, bus in enumerate(machine.transmitters):
            if bus.rtu is not None:
                lines.setdefault(bus.rtu.port, []).append((("machines", m, "transmitters", b), bus))
    return lines


def check_shared_lines(machines: Sequence[MachineSection]) -> None:
    """Refuse two line settings or one device id twice on one port (:class:`KeyPathError`)."""
    for port, buses in _rtu_buses(machines).items():
        first_where, first = buses[0]
        assert first.rtu is not None
        settings = {
            "baudrate": ("baud rate", "{} baud", "at {} baud"),
            "parity": ("parity", "parity {}", "with parity {}"),
        }
        owners: dict[int, Where] = {}
        for where, bus in buses:
            assert bus.rtu is not None
            for key, (what, given, runs) in settings.items():
                mine, theirs = getattr(bus.rtu, key), getattr(first.rtu, key)
                if mine != theirs:
                    raise KeyPathError(
                        (*where, "rtu", key),
                        f"{given.format(mine)} given, but port {port} already runs "
                        f"{runs.format(theirs)} for {_owner(machines, first_where)}; "
                        f"one RS-485 line has one {what}",
                    )
            for d, device in enumerate(bus.devices):
                owner = owners.get(device.device_id)
                if owner is not None:
                    raise KeyPathError(
                        (*where, "devices", d, "device_id"),
                        f"device {device.device_id} on port {port} is already read by "
                        f"{_owner(machines, owner)}; one device id per RS-485 line",
                    )
                owners[device.device_id] = (*where, "devices", d)


def _owner(machines: Sequence[MachineSection], where: Where) -> str:
    """``machine 'vmc-1' (machines[0].transmitters[0])`` for a key path below a machine."""
    machine = machines[int(where[1])]
    return f"machine '{machine.id}' ({format_path(where)})"


def shared_hubs(machines: Sequence[MachineSection]) -> dict[str, BusHub]:
    """One hub per serial port of the configuration (checked by :func:`check_shared_lines`)."""
    hubs = {}
    for port, buses in _rtu_buses(machines).items():
        rtus = [bus.rtu for _, bus in buses if bus.rtu is not None]
        line = rtus[0]
        if any((r.baudrate, r.parity) != (line.baudrate, line.parity) for r in rtus):
            raise ValueError(f"port {port}: buses disagree on baud rate or parity")
        link = ModbusConnection(
            serial_port=port,
            baudrate=line.baudrate,
            parity=line.parity,
            timeout_s=max(bus.timeout_s for _, bus in buses),
            name=", ".join(dict.fromkeys(bus.name for _, bus in buses)),
        )
        silence_s = max(rtu_silence_s(line.baudrate), *(r.min_silence_s for r in rtus))
        hubs[port] = BusHub(link, silence_s=silence_s)
    return hubs
