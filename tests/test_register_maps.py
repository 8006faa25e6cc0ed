"""Register maps as data: loaded from files, served and read over real pymodbus servers.

The simulated devices encode with the same map the gateway decodes with, so they
agree by construction; a raw pymodbus client checks independently that the wire
really carries the declared byte and word order. Telegraf-style workarounds are
observed from the server's side (the requests it received, and when).
"""

from __future__ import annotations

import asyncio
import itertools
import math
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import pytest
import yaml
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.client.mixin import ModbusClientMixin

from drivers.cnc import SpeedReading
from drivers.cnc_modbus import ModbusCnc
from drivers.register_map import DeviceRegisters, ReadRequest
from drivers.schema import MAPS_DIR, RegisterMap, load_register_map
from drivers.transmitters import ChannelResult, DeviceMap, TransmitterBus, decode_channels
from drivers.yaml_loader import YamlError
from gateway.config import ConfigError, load_config
from simulator.link import ChannelReading, ChannelStatus, FixedLink, MachineSnapshot, RunMode
from simulator.servers.modbus_cnc import CncModbusServer
from simulator.servers.modbus_common import ReceivedRequest
from simulator.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from tests.cli import ROOT, gateway_in_process
from tests.ports import free_tcp_port

T = TypeVar("T")
HOST = "127.0.0.1"
FLOAT32 = ModbusClientMixin.DATATYPE.FLOAT32
CHANNELS = ["T1", "T2", "T3", "T4", "T5", "T6"]

SNAPSHOT = MachineSnapshot(
    time_s=0.0,
    channels={
        "T1": ChannelReading(23.5),
        "T2": ChannelReading(-5.2),
        "T3": ChannelReading(math.nan, ChannelStatus.OPEN_CIRCUIT),  # broken wire
        "T4": ChannelReading(30.0, ChannelStatus.SHORT_CIRCUIT),
        "T5": ChannelReading(61.25),
        # T6 is not in the snapshot: an unplugged probe, reported as open circuit
    },
    actual_speed_rpm=4000.0,
    commanded_speed_rpm=4500.0,
    run_mode=RunMode.AUTO,
    macros={500: 0.0125},
    probe_error_um=3.25,
)
#: What the gateway must report, whatever the map's byte and word order.
EXPECTED = {
    "T1": ChannelResult("T1", 23.5, 0, None),
    "T2": ChannelResult("T2", -5.2, 0, None),
    "T3": ChannelResult("T3", None, 1, "open circuit"),
    "T4": ChannelResult("T4", None, 2, "short circuit"),
    "T5": ChannelResult("T5", 61.3, 0, None),  # 612.5 counts, ties away from zero
    "T6": ChannelResult("T6", None, 1, "open circuit"),
}


def run(body: Callable[[], Awaitable[T]]) -> T:
    return asyncio.run(asyncio.wait_for(body(), 60))


def shipped(name: str) -> dict[str, object]:
    return yaml.safe_load((MAPS_DIR / f"{name}.yaml").read_text(encoding="utf-8"))


def float_pt100(byte_order: str, word_order: str) -> dict[str, object]:
    """A Pt100 module that reports float32 °C (two registers a channel), in the given order."""
    fields: list[dict[str, object]] = [
        {"name": f"ch{i + 1}_C", "address": 2 * i, "data_type": "float32"} for i in range(8)
    ]
    for i in range(8):
        fields[i]["status"] = f"ch{i + 1}_status"
        fields.append({"name": f"ch{i + 1}_status", "address": 16 + i, "data_type": "uint16"})
    return {
        "name": "pt100_float",
        "register_type": "input",
        "byte_order": byte_order,
        "word_order": word_order,
        "faults": {
            "status_codes": {"ok": 0, "open_circuit": 1, "short_circuit": 2, "out_of_range": 3},
            "value_codes": {"open_circuit": -9999.0, "short_circuit": 9999.0},
        },
        "channels": [f"ch{i + 1}_C" for i in range(8)],
        "fields": fields,
    }


def write_map(path: Path, data: dict[str, object]) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def maps_in_order(tmp_path: Path, order: str) -> tuple[RegisterMap, RegisterMap]:
    """(transmitter map, CNC map) loaded from files, in the byte/word order ``order``."""
    if order == "big/big":  # the shipped files as they are
        return (
            load_register_map(str(MAPS_DIR / "pt100_8ch.yaml")),
            load_register_map(str(MAPS_DIR / "sim_cnc.yaml")),
        )
    byte_order, word_order = order.split("/")
    cnc = shipped("sim_cnc") | {"name": "cnc_swapped", "byte_order": byte_order}
    cnc["word_order"] = word_order
    pt100 = write_map(tmp_path / "pt100_float.yaml", float_pt100(byte_order, word_order))
    return (
        load_register_map(str(pt100)),
        load_register_map(str(write_map(tmp_path / "cnc.yaml", cnc))),
    )


async def raw_registers(port: int, function_code: int, address: int, count: int) -> list[int]:
    """Registers as the wire carries them, read by a plain pymodbus client."""
    client = AsyncModbusTcpClient(HOST, port=port, timeout=1.0, retries=0)
    assert await client.connect()
    try:
        read = client.read_input_registers if function_code == 4 else client.read_holding_registers
        reply = await read(address, count=count, device_id=1)
        assert not reply.isError(), reply
        return list(reply.registers)
    finally:
        client.close()


def wire(value: float, order: str) -> list[int]:
    """A float32 on the wire in ``order``, by pymodbus's conversion and a byte swap."""
    byte_order, word_order = order.split("/")
    registers = ModbusClientMixin.convert_to_registers(value, FLOAT32, word_order=word_order)
    if byte_order == "little":
        registers = [((r & 0xFF) << 8) | (r >> 8) for r in registers]
    return registers


@pytest.mark.parametrize("order", ["big/big", "big/little", "little/little"])
def test_pt100_and_cnc_through_maps_from_files(tmp_path: Path, order: str) -> None:
    transmitter_map, cnc_map = maps_in_order(tmp_path, order)

    async def body() -> None:
        link = FixedLink(SNAPSHOT)
        modules = TransmitterServer(
            link,
            [TransmitterDevice(1, CHANNELS, DeviceRegisters(transmitter_map))],
            tcp=(HOST, 0),
        )
        cnc_server = CncModbusServer(
            link, host=HOST, port=free_tcp_port(), registers=DeviceRegisters(cnc_map)
        )
        async with modules, cnc_server:
            bus_port, cnc_port = modules.address[1], cnc_server.address[1]
            bus = TransmitterBus(
                [DeviceMap(1, tuple(CHANNELS), DeviceRegisters(transmitter_map))],
                tcp=(HOST, bus_port),
                timeout_s=0.5,
            )
            cnc = ModbusCnc(HOST, cnc_port, timeout_s=0.5, register_map=cnc_map)
            expected = dict(EXPECTED)
            if order != "big/big":  # float32 carries 61.25 as it is; int16 counts round it
                expected["T5"] = ChannelResult("T5", 61.25, 0, None)
            try:
                assert await bus.read_all(0.0) == expected
                assert await cnc.read_speed() == SpeedReading(4000.0, 4500.0, int(RunMode.AUTO))
                assert await cnc.read_macro(500) == 0.0125
                await cnc.write_macro(501, -0.0375)
                assert link.writes[-1] == (501, -0.0375)
                assert await cnc.read_macro(501) == -0.0375
            finally:
                await bus.close()
                await cnc.close()
            # The wire carries the declared order (checked apart from the map's own code).
            speed = await raw_registers(cnc_port, 3, 0, 2)
            macro = await raw_registers(cnc_port, 3, 1002, 2)
            if order == "big/big":
                assert speed == [0x457A, 0x0000]  # 4000.0, high word first
                assert (await raw_registers(bus_port, 4, 0, 1)) == [235]
            else:
                assert speed == wire(4000.0, order) != [0x457A, 0x0000]
                assert macro == wire(-0.0375, order)
                assert (await raw_registers(bus_port, 4, 0, 2)) == wire(23.5, order)
                # T3's open circuit: the value code and the status (registers 4–5, 18)
                assert (await raw_registers(bus_port, 4, 4, 2)) == wire(-9999.0, order)
                status = [1] if order.startswith("big") else [0x0100]
                assert (await raw_registers(bus_port, 4, 18, 1)) == status

    run(body)


def test_a_client_with_the_wrong_word_order_reads_another_value(tmp_path: Path) -> None:
    """The order in the map matters: the shipped big/big map misreads a swapped CNC."""
    _, swapped = maps_in_order(tmp_path, "big/little")

    async def body() -> None:
        link = FixedLink(SNAPSHOT)
        server = CncModbusServer(
            link, host=HOST, port=free_tcp_port(), registers=DeviceRegisters(swapped)
        )
        async with server:
            wrong = ModbusCnc(HOST, server.address[1], timeout_s=0.5)
            try:
                assert (await wrong.read_speed()).actual_rpm != 4000.0
            finally:
                await wrong.close()

    run(body)


def test_reads_are_grouped_into_contiguous_blocks() -> None:
    pt100 = DeviceRegisters(load_register_map("pt100_8ch"))
    assert pt100.requests == (ReadRequest("input", 0, 16),)
    cnc = DeviceRegisters(load_register_map("sim_cnc"))
    assert cnc.requests == (ReadRequest("holding", 0, 7),)
    gappy = RegisterMap.model_validate(
        {
            "fields": [
                {"name": "a", "address": 0, "data_type": "float32"},
                {"name": "b", "address": 2, "data_type": "uint16"},
                {"name": "c", "address": 10, "data_type": "int32", "word_order": "little"},
                {"name": "d", "address": 0, "data_type": "uint16", "register_type": "input"},
            ]
        }
    )
    layout = DeviceRegisters(gappy)
    assert layout.requests == (
        ReadRequest("holding", 0, 3),
        ReadRequest("holding", 10, 2),
        ReadRequest("input", 0, 1),
    )
    words = [0x457A, 0, 7, 0xFFFF, 0xFFFE, 42]  # c: low word first → 0xFFFEFFFF = −65537
    assert layout.decode(words) == {"a": 4000.0, "b": 7, "c": -65537, "d": 42}
    split = DeviceRegisters(
        gappy, gappy.workarounds.model_copy(update={"max_registers_per_request": 2})
    )
    # A field never straddles two requests: a (2 registers) alone, then b.
    assert split.requests[:2] == (ReadRequest("holding", 0, 2), ReadRequest("holding", 2, 1))


@pytest.mark.parametrize(
    ("workarounds", "expected"),
    [
        ({}, [(4, 0, 16)]),
        ({"max_registers_per_request": 5}, [(4, 0, 5), (4, 5, 5), (4, 10, 5), (4, 15, 1)]),
        ({"one_request_per_field": True}, [(4, a, 1) for a in range(16)]),
    ],
)
def test_workarounds_shape_the_requests_the_device_receives(
    workarounds: dict[str, object], expected: list[tuple[int, int, int]]
) -> None:
    received = read_with_workarounds(workarounds, cycles=1)
    assert [(r.function_code, r.address, r.count) for r in received] == expected


def test_a_pause_between_requests_is_kept_on_the_wire() -> None:
    pause_s = 0.08
    workarounds = {"pause_between_requests_s": pause_s, "max_registers_per_request": 8}
    times = [r.at_s for r in read_with_workarounds(workarounds, cycles=2)]
    assert len(times) == 4  # two requests a cycle
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert min(gaps) >= pause_s - 0.002, gaps


def read_with_workarounds(workarounds: dict[str, object], cycles: int) -> list[ReceivedRequest]:
    """Read the Pt100 module ``cycles`` times through its map with ``workarounds``
    over Modbus TCP; the requests the server received (each cycle's reading checked)."""
    pt100 = load_register_map("pt100_8ch")
    quirky = pt100.model_copy(
        update={"workarounds": pt100.workarounds.model_copy(update=workarounds)}
    )

    async def body() -> list[ReceivedRequest]:
        link = FixedLink(SNAPSHOT)
        async with TransmitterServer(
            link, [TransmitterDevice(1, CHANNELS)], tcp=(HOST, 0)
        ) as server:
            bus = TransmitterBus(
                [DeviceMap(1, tuple(CHANNELS), DeviceRegisters(quirky))],
                tcp=server.address,
                timeout_s=0.5,
            )
            try:
                for cycle in range(cycles):
                    assert await bus.read_all(float(cycle)) == EXPECTED
            finally:
                await bus.close()
            return list(server.received)

    return run(body)


# -- bad maps: one located error --------------------------------------------------------

CONFIG = (ROOT / "config.yaml").read_text(encoding="utf-8")
DEVICE_2 = (
    "          - {device_id: 2, channels: [T9, null]}   # channel 2 carries the ambient sensor"
)


def config_naming(tmp_path: Path, map_source: str) -> Path:
    assert DEVICE_2 in CONFIG
    text = CONFIG.replace(
        DEVICE_2, f"          - {{device_id: 2, channels: [T9, null], map: {map_source}}}"
    )
    path = tmp_path / "config.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def mutated_pt100(tmp_path: Path, old: str, new: str) -> tuple[Path, int]:
    """The shipped Pt100 map with one mutation, and the line it is on."""
    text = (MAPS_DIR / "pt100_8ch.yaml").read_text(encoding="utf-8")
    assert text.count(old) == 1
    line = text[: text.index(old)].count("\n") + 1
    path = tmp_path / "maps" / "pt100_bad.yaml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(text.replace(old, new), encoding="utf-8")
    return path, line


@pytest.mark.parametrize(
    ("old", "new", "key", "message"),
    [
        (
            "address: 2, data_type: int16",
            "address: 2, data_type: int17",
            "fields[2].data_type",
            "Input should be 'int16', 'uint16'",
        ),
        (
            "address: 9, data_type: uint16",
            "address: 8, data_type: uint16",
            "fields[9].address",
            "input register 8 is already field 'ch1_status'; fields must not overlap",
        ),
        (
            "word_order: big",
            "word_order: big\nworkarounds: {max_registers_per_request: 200}",
            "workarounds.max_registers_per_request",
            "Input should be less than or equal to 125",
        ),
        (
            "address: 4, data_type: int16, scale: 0.1",
            "address: 4, data_type: int16, scael: 0.1",
            "fields[4].scael",
            "unknown key (not part of the configuration)",
        ),
    ],
)
def test_a_bad_map_file_is_one_error_naming_its_file_line_and_key(
    tmp_path: Path, old: str, new: str, key: str, message: str
) -> None:
    path, line = mutated_pt100(tmp_path, old, new)
    if key.startswith("workarounds"):
        line += 1
    with pytest.raises(ConfigError) as refused:
        load_config(config_naming(tmp_path, "maps/pt100_bad.yaml"))
    assert str(refused.value).startswith(f"{path}:{line}: {key}: {message}"), refused.value


def test_check_config_names_the_map_file_exits_2_without_traceback(tmp_path: Path) -> None:
    path, line = mutated_pt100(
        tmp_path, "address: 2, data_type: int16", "address: 2, data_type: int17"
    )
    result = gateway_in_process(
        "check-config", "--config", config_naming(tmp_path, "maps/pt100_bad.yaml")
    )
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stdout + result.stderr
    assert lines[0].startswith(f"error: {path}:{line}: fields[2].data_type: Input should be")


def test_a_map_file_names_its_own_line_when_loaded_alone(tmp_path: Path) -> None:
    path, line = mutated_pt100(tmp_path, "channels: [ch1_C,", "channels: [ch9_C,")
    with pytest.raises(YamlError, match=rf"^{path}:{line}: channels\[0\]: no field named 'ch9_C'"):
        load_register_map(str(path))


def test_a_device_names_a_map_by_name_or_path_and_the_default_is_the_pt100(tmp_path: Path) -> None:
    plain = load_config(ROOT / "config.yaml").machines[0].transmitters[0].devices[0]
    assert plain.map == load_register_map("pt100_8ch")
    copy = tmp_path / "copy.yaml"
    copy.write_text((MAPS_DIR / "pt100_8ch.yaml").read_text(encoding="utf-8"), encoding="utf-8")
    named = load_config(config_naming(tmp_path, "copy.yaml")).machines[0].transmitters[0]
    assert named.devices[1].map == plain.map
    with pytest.raises(
        ConfigError, match=r"config.yaml:\d+: machines\[0\].*map: no register map 'pt9'"
    ):
        load_config(config_naming(tmp_path, "pt9"))


def test_decoding_reuses_only_what_did_not_change() -> None:
    device = DeviceMap(1, ("T1", "T2", None, "T4"))
    registers = [235, 0xFFCC, 0, 0x7FFF] + [0] * 4 + [0, 0, 0, 0] + [0] * 4
    first = decode_channels(device, registers)
    assert first["T1"] == ChannelResult("T1", 23.5, 0, None)
    assert first["T4"] == ChannelResult("T4", None, 0, "fault code 32767 with status OK")
    again = decode_channels(device, list(registers))
    assert again == first and again is not first  # the caller may change its copy
    registers[0], registers[11] = 236, 1  # T1 warms by one count, T4's status says open
    changed = decode_channels(device, registers)
    assert changed["T1"] == ChannelResult("T1", 23.6, 0, None)
    assert changed["T4"] == ChannelResult("T4", None, 1, "open circuit")
    assert changed["T2"] is first["T2"]  # unchanged channel: the same result object
