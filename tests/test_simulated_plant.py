"""The whole simulated plant over its protocols: the real machine behind real endpoints.

Transmitters on an RTU bus (socat pty pair) and on Modbus TCP, the CNC over
OPC UA and Modbus TCP, all fed by one SimulatedMachine on a manual clock. A
client writes the compensation macro and the machine's measured error moves
by exactly that amount: the loop is closed.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest
from asyncua import Client, ua
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient

from drivers.clock import ManualClock
from simulator.serve import SimulatedPlant, SimulatorConfig
from tests.ports import free_tcp_port, wait_for_port
from tests.serial_pty import socat_pty_pair
from tests.served_bench import gateway_process

NAMESPACE = "urn:spindle-gateway:simulated-cnc"


def plant_config(rtu_port: str, opcua_port: int) -> SimulatorConfig:
    return SimulatorConfig.model_validate(
        {
            "program": "const8000",
            "seed": 4,
            "transmitters": {
                "rtu": {
                    "port": rtu_port,
                    "devices": [{"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]}],
                },
                "tcp": {
                    "port": free_tcp_port(),
                    "devices": [{"device_id": 2, "channels": ["T9", "ambient"]}],
                },
            },
            "cnc": {"opcua": {"port": opcua_port}, "modbus": {"port": free_tcp_port()}},
        }
    )


def temperatures_from(registers: list[int], count: int) -> list[float]:
    return [(r - 65536 if r >= 32768 else r) / 10.0 for r in registers[:count]]


async def exercise_plant(tmp_path: Path) -> dict[str, object]:
    clock = ManualClock()
    found: dict[str, object] = {}
    with socat_pty_pair(tmp_path) as pty:
        plant = SimulatedPlant(plant_config(pty.server_port, free_tcp_port()), clock=clock)
        machine = plant.machine
        async with plant:
            clock.advance(3 * 3600.0)
            await plant.update()
            truth = machine.readings()  # fresh noise; compare within noise + resolution

            rtu = AsyncModbusSerialClient(pty.client_port, baudrate=19200, timeout=2)
            await rtu.connect()
            rr = await rtu.read_input_registers(0, count=16, device_id=1)
            rtu.close()
            found["rtu_C"] = temperatures_from(rr.registers, 8)
            found["rtu_status"] = rr.registers[8:16]

            host, port = plant.tcp_transmitters.address
            tcp = AsyncModbusTcpClient(host, port=port, timeout=2)
            await tcp.connect()
            rr = await tcp.read_input_registers(0, count=2, device_id=2)
            found["tcp_C"] = temperatures_from(rr.registers, 2)
            tcp.close()

            host, port = plant.cnc_modbus.address
            cnc = AsyncModbusTcpClient(host, port=port, timeout=2)
            await cnc.connect()
            rr = await cnc.read_holding_registers(0, count=2, device_id=1)
            found["modbus_speed_rpm"] = cnc.convert_from_registers(
                rr.registers, cnc.DATATYPE.FLOAT32, word_order="big"
            )
            cnc.close()

            found["truth_C"] = {name: r.value_C for name, r in truth.items()}
            found["growth_um"] = machine.growth_um()
            async with Client(plant.cnc_opcua.endpoint) as client:
                idx = await client.get_namespace_index(NAMESPACE)
                speed = await client.get_node(f"ns={idx};s=Spindle.ActualSpeed").read_value()
                found["opcua_speed_rpm"] = speed
                before = machine.true_error_um()
                compensation_mm = round(machine.growth_um() / 1000.0, 4)
                node = client.get_node(f"ns={idx};s=Macro.500")
                await node.write_value(
                    ua.DataValue(ua.Variant(compensation_mm, ua.VariantType.Double))
                )
                await asyncio.sleep(0.05)
                found["error_before_um"] = before
                found["error_after_um"] = machine.true_error_um()
                found["compensation_mm"] = compensation_mm
                found["macro_log"] = list(machine.compensation_log)
                await plant.update()
                found["macro_read_back"] = await node.read_value()
    return found


def test_plant_serves_the_machine_and_closes_the_loop(tmp_path: Path) -> None:
    found = asyncio.run(exercise_plant(tmp_path))
    truth = found["truth_C"]
    # Every channel agrees with the machine within noise (σ 0.03 °C) and the 0.1 °C step.
    for i, value in enumerate(found["rtu_C"]):
        assert value == pytest.approx(truth[f"T{i + 1}"], abs=0.2)
    assert found["rtu_status"] == [0] * 8
    assert found["tcp_C"] == pytest.approx([truth["T9"], truth["ambient"]], abs=0.2)
    assert found["modbus_speed_rpm"] == 8000.0
    assert found["opcua_speed_rpm"] == 8000.0
    # After three hours at 8000 r/min the spindle has grown; the bearing is warm.
    assert found["growth_um"] > 20.0
    assert np.mean(found["rtu_C"][:5]) > 25.0
    # The compensation written over OPC UA is applied to the tool position at once.
    assert found["error_before_um"] > 20.0
    assert found["error_after_um"] == pytest.approx(
        found["error_before_um"] - found["compensation_mm"] * 1000.0, abs=1e-9
    )
    assert abs(found["error_after_um"]) < 0.1
    assert [value for _, value in found["macro_log"]] == [found["compensation_mm"]]
    assert found["macro_read_back"] == found["compensation_mm"]


async def node_opcua_compensates(tmp_path: Path) -> dict[str, float]:
    from tests.test_opcua_cnc import run_node_client

    clock = ManualClock()
    config = SimulatorConfig.model_validate(
        {"program": "const6000", "seed": 2, "cnc": {"opcua": {"port": free_tcp_port()}}}
    )
    async with SimulatedPlant(config, clock=clock) as plant:
        clock.advance(2 * 3600.0)
        await plant.update()
        before = plant.machine.true_error_um()
        compensation_mm = round(plant.machine.growth_um() / 1000.0, 4)
        result = await run_node_client(
            plant.cnc_opcua.endpoint,
            [{"write": "Macro.500", "value": compensation_mm}, {"read": "Macro.500"}],
            tmp_path / "pki",
        )
        return {
            "before_um": before,
            "after_um": plant.machine.true_error_um(),
            "compensation_mm": compensation_mm,
            "write_status": result["results"][0]["status"],
            "read_back": result["results"][1]["value"],
        }


def test_node_opcua_write_is_applied_to_the_measured_error(tmp_path: Path) -> None:
    found = asyncio.run(node_opcua_compensates(tmp_path))
    assert found["write_status"] == "Good"
    assert found["read_back"] == found["compensation_mm"]
    assert found["before_um"] > 15.0
    assert found["after_um"] == pytest.approx(
        found["before_um"] - 1000.0 * found["compensation_mm"], abs=1e-9
    )


def test_simulate_serves_config_yaml_until_interrupted(tmp_path: Path) -> None:
    import signal
    import subprocess

    import yaml

    bus_port, cnc_port = free_tcp_port(), free_tcp_port()
    config = tmp_path / "config.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "simulator": {
                    "program": "const4000",
                    "speedup": 600,
                    "transmitters": {
                        "tcp": {
                            "port": bus_port,
                            "devices": [{"device_id": 1, "channels": ["T1", "T2"]}],
                        }
                    },
                    "cnc": {"modbus": {"port": cnc_port}},
                }
            }
        )
    )
    proc = gateway_process("simulate", "--config", config)
    try:
        wait_for_port(cnc_port, timeout_s=20)
        mbpoll = ["mbpoll", "-m", "tcp", "-a", "1", "-1", "-r", "1"]
        speed = subprocess.run(
            [*mbpoll, "-p", str(cnc_port), "-t", "4:float", "-B", "-c", "1", "127.0.0.1"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        temps = subprocess.run(
            [*mbpoll, "-p", str(bus_port), "-t", "3", "-c", "2", "127.0.0.1"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    assert speed.returncode == 0, speed.stderr
    assert (
        "[1]: \t4000" in speed.stdout.replace(" ", "\t").replace("\t\t", "\t")
        or "4000" in speed.stdout
    )
    values = [int(line.split(":")[1]) for line in temps.stdout.splitlines() if line.startswith("[")]
    assert len(values) == 2 and all(180 <= v <= 400 for v in values)  # 18–40 °C in 0.1 °C
    assert "serving simulated machine 'vmc-8000'" in out
    assert proc.returncode in (0, -signal.SIGINT), err


@pytest.mark.parametrize("stop_signal", ["SIGINT", "SIGTERM"])
def test_simulate_stops_on_sigint_or_sigterm_even_started_with_sigint_ignored(
    tmp_path: Path, stop_signal: str
) -> None:
    """A shell script that starts the simulator in the background hands it SIGINT as
    ignored; the interpreter's own Ctrl-C then never fires, so it sets its handlers."""
    import signal
    import socket
    import subprocess
    import sys
    import time

    import yaml

    cnc_port = free_tcp_port()
    config = tmp_path / "config.yaml"
    simulator = {"program": "const4000", "speedup": 600, "cnc": {"modbus": {"port": cnc_port}}}
    config.write_text(yaml.safe_dump({"simulator": simulator}))
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway", "simulate", "--config", str(config)],
        cwd=Path(__file__).resolve().parent.parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        wait_for_port(cnc_port, timeout_s=20)
        sent = time.monotonic()
        proc.send_signal(getattr(signal, stop_signal))
        out, err = proc.communicate(timeout=10)
        stopped_s = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out.splitlines()[-1] == "stopped"
    assert stopped_s < 3.0
    with pytest.raises(OSError):  # the endpoints were closed, not left to the exit
        socket.create_connection(("127.0.0.1", cnc_port), timeout=1).close()
