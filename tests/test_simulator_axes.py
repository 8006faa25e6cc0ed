"""The simulated machine grows in X and Y too, each from its own physics, not a copy of Z.

X: the motor on one side of the headstock warms that face first (a 300 s face)
before the heat crosses the casting (a 2400 s face): X rises under load, peaks,
comes partly back, and goes negative in the cool-down. Y: the front (bearing) face
against the rear (motor) face: its sign follows the speed. Both are served and
compensated through their own macros, like Z.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from asyncua import Client, ua
from pymodbus.client import AsyncModbusTcpClient

from drivers.clock import ManualClock
from simulator.axes import AxisFaces
from simulator.machine import SimulatedMachine
from simulator.params import NODES, load_params
from simulator.programs import SpeedProgram, program_by_name
from simulator.record import record
from simulator.serve import SimulatedPlant, SimulatorConfig
from tests.ports import free_tcp_port

PARAMS = load_params()
NAMESPACE = "urn:spindle-gateway:simulated-cnc"


def columns(program: str, seed: int = 1, params=PARAMS) -> dict[str, np.ndarray]:
    """One recorded run (10 min rest first) as columns."""
    rec = record(params, [program_by_name(program)], seed=seed)
    values = list(zip(*rec.rows, strict=True))
    return {
        name: np.array(col, dtype=float)
        for name, col in zip(rec.header[1:], values[1:], strict=True)
    }


def residual_share(y: np.ndarray, x: np.ndarray) -> float:
    """RMS of what the best ``a·x + b`` leaves of ``y``, as a share of y's spread."""
    design = np.column_stack([x, np.ones_like(x)])
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    return float(np.sqrt(np.mean((y - design @ coef) ** 2)) / np.std(y))


def test_each_face_follows_its_nodes_with_its_own_time_constant() -> None:
    """A step on the motor node alone: each face reaches 1 − 1/e of its mix at its τ."""
    x = PARAMS.axes["X"]
    faces = AxisFaces({"X": x}, step_s=PARAMS.sub_step_s, start_C=0.0)
    nodes = np.zeros(len(NODES))
    nodes[NODES.index("motor")] = 10.0
    hot, cold = x.hot_face, x.cold_face
    for _ in range(round(hot.tau_s / PARAMS.sub_step_s)):
        faces.step(nodes)
    assert faces.faces_C[0] == pytest.approx(10.0 * hot.mix["motor"] * (1 - math.exp(-1)))
    for _ in range(round((cold.tau_s - hot.tau_s) / PARAMS.sub_step_s)):
        faces.step(nodes)
    assert faces.faces_C[1] == pytest.approx(10.0 * cold.mix["motor"] * (1 - math.exp(-1)))
    assert faces.growth_um()["X"] == pytest.approx(
        x.um_per_K * (faces.faces_C[0] - faces.faces_C[1])
    )


def test_x_grows_under_load_peaks_early_comes_back_and_reverses_when_cooling() -> None:
    run = columns("const8000")
    t, speed, x, z = run["time_s"], run["speed_rpm"], run["x_um"], run["error_um"]
    loaded = speed > 0
    peak = int(np.argmax(x))
    start = t[loaded][0]
    # Positive (+X) under load, the peak within 40–120 min of the start.
    assert x[peak] > 10.0 and 2400.0 < t[peak] - start < 7200.0
    assert np.all(x[loaded & (t > start + 900.0)] > 2.0)
    # Z keeps rising to the end of the load while X has come back by a quarter or more.
    last_loaded = np.flatnonzero(loaded)[-1]
    assert x[last_loaded] < 0.75 * x[peak]
    assert z[last_loaded] > z[loaded].max() - 1.0  # within the probe noise of its top
    # Cooling: the far face is still warm when the motor side has cooled, X goes negative.
    assert x[~loaded & (t > t[last_loaded])].min() < -2.0


def test_y_changes_sign_with_speed() -> None:
    """Bearing heat ∝ n^1.5 at the front, motor heat ∝ n at the rear: −Y fast, +Y slow."""
    fast, slow = columns("const8000"), columns("const2000")
    first_hour = (fast["speed_rpm"] > 0) & (fast["time_s"] < 600.0 + 3600.0)
    assert fast["y_um"][first_hour].min() < -4.0
    assert np.all(fast["y_um"][first_hour & (fast["time_s"] > 1500.0)] < 0.0)
    assert slow["y_um"][slow["speed_rpm"] > 0].max() > 2.0
    assert slow["y_um"][slow["speed_rpm"] > 0].min() > -1.0


@pytest.mark.parametrize("program", ["iso230-spectrum", "production-7"])
def test_x_and_y_are_not_a_scaled_z(program: str) -> None:
    run = columns(program)
    z = run["error_um"]
    # The best scaled-and-shifted Z leaves most of X and nearly all of Y.
    assert residual_share(run["x_um"], z) > 0.6
    assert residual_share(run["y_um"], z) > 0.85
    assert abs(np.corrcoef(run["y_um"], z)[0, 1]) < 0.5
    assert np.corrcoef(run["x_um"], z)[0, 1] < 0.8


def test_the_z_column_is_unchanged_by_the_other_axes() -> None:
    """With or without X and Y, a recording's temperatures and Z error are the same."""
    with_axes = record(PARAMS, [program_by_name("iso230-spectrum")], seed=3)
    alone = record(
        PARAMS.model_copy(update={"axes": {}}), [program_by_name("iso230-spectrum")], seed=3
    )
    assert with_axes.header == (*alone.header, "x_um", "y_um")
    assert [row[:-2] for row in with_axes.rows] == alone.rows
    lines = with_axes.to_csv().splitlines()
    assert lines[0].endswith(",ambient_C,error_um,x_um,y_um")
    assert all(len(line.split(",")) == len(with_axes.header) for line in lines)


def test_each_axis_compensation_removes_that_axis_error_only() -> None:
    program = SpeedProgram("load", ((4 * 3600.0, 8000.0),))
    machine = SimulatedMachine(PARAMS, program, seed=2)
    machine.advance_to(3600.0)
    grown = {axis: machine.axis_growth_um(axis) for axis in ("X", "Y", "Z")}
    assert grown["X"] > 10.0 and grown["Y"] < -3.0 and grown["Z"] > 10.0
    machine.write_macro(PARAMS.axes["X"].compensation.macro, grown["X"] / 1000.0)
    assert machine.axis_true_error_um("X") == pytest.approx(0.0, abs=1e-9)
    assert machine.axis_true_error_um("Y") == pytest.approx(grown["Y"], abs=1e-9)
    assert machine.true_error_um() == pytest.approx(grown["Z"], abs=1e-9)
    machine.write_macro(PARAMS.axes["Y"].compensation.macro, grown["Y"] / 1000.0)
    assert machine.axis_true_error_um("Y") == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="no axis 'W'"):
        machine.axis_growth_um("W")


def test_axes_sharing_a_macro_or_a_column_are_refused() -> None:
    with pytest.raises(ValueError, match=r"axes\.Y: macro #502 is already used"):
        load_params({"axes": {"Y": {"compensation": {"macro": 502}}}})
    with pytest.raises(ValueError, match=r"axes\.X: macro #600 is already used"):
        load_params({"axes": {"X": {"probe_macro": 600}}})
    with pytest.raises(ValueError, match="'x_um' is already used"):
        load_params({"axes": {"Y": {"column": "x_um"}}})
    with pytest.raises(ValueError, match="expected X or Y"):
        load_params({"axes": {"Z": PARAMS.axes["X"].model_dump()}})


def test_same_seed_same_x_and_y_other_seed_other_noise() -> None:
    a, b, c = (columns("const4000", seed=s) for s in (5, 5, 6))
    for name in ("x_um", "y_um"):
        assert np.array_equal(a[name], b[name])
        assert not np.array_equal(a[name], c[name])
        assert np.max(np.abs(a[name] - c[name])) < 2.0  # the probe's noise, not the physics


async def served_axes(clock: ManualClock) -> dict[str, float]:
    """X compensated over OPC UA; X's probe value read back over Modbus TCP."""
    plant = SimulatedPlant(
        SimulatorConfig.model_validate(
            {
                "program": "const8000",
                "seed": 4,
                "transmitters": {
                    "tcp": {
                        "port": free_tcp_port(),
                        "devices": [{"device_id": 1, "channels": ["T1"]}],
                    }
                },
                "cnc": {"opcua": {"port": free_tcp_port()}, "modbus": {"port": free_tcp_port()}},
            }
        ),
        clock=clock,
    )
    machine = plant.machine
    found: dict[str, float] = {}
    async with plant:
        clock.advance(2 * 3600.0)
        await plant.update()
        found["x_before_um"] = machine.axis_true_error_um("X")
        found["z_before_um"] = machine.true_error_um()
        compensation_mm = round(machine.axis_growth_um("X") / 1000.0, 4)
        async with Client(plant.cnc_opcua.endpoint) as client:
            idx = await client.get_namespace_index(NAMESPACE)
            node = client.get_node(f"ns={idx};s=Macro.502")
            await node.write_value(ua.DataValue(ua.Variant(compensation_mm, ua.VariantType.Double)))
            await asyncio.sleep(0.05)
        found["x_after_um"] = machine.axis_true_error_um("X")
        found["z_after_um"] = machine.true_error_um()
        found["compensation_mm"] = compensation_mm
        clock.advance(PARAMS.probe.period_s)
        await plant.update()
        found["x_probe_um"] = machine.macros[602]
        host, port = plant.cnc_modbus.address
        cnc = AsyncModbusTcpClient(host, port=port, timeout=2)
        await cnc.connect()
        found["x_probe_modbus_um"] = await read_macro(cnc, 602)
        cnc.close()
    return found


async def read_macro(cnc: AsyncModbusTcpClient, number: int) -> float:
    """Macro #number over the CNC's Modbus map (float32, big-endian words)."""
    from simulator.servers.modbus_cnc import macro_register

    rr = await cnc.read_holding_registers(macro_register(number), count=2, device_id=1)
    return float(cnc.convert_from_registers(rr.registers, cnc.DATATYPE.FLOAT32, word_order="big"))


def test_served_x_compensation_and_probe() -> None:
    found = asyncio.run(served_axes(ManualClock()))
    assert found["x_before_um"] > 10.0
    assert found["x_after_um"] == pytest.approx(
        found["x_before_um"] - found["compensation_mm"] * 1000.0, abs=1e-9
    )
    assert abs(found["x_after_um"]) < 0.1
    assert found["z_after_um"] == found["z_before_um"]  # Z's macro untouched
    # The probe publishes X's remaining error at #602, over OPC UA's and Modbus's macros.
    assert abs(found["x_probe_um"]) < 2.0
    assert found["x_probe_modbus_um"] == pytest.approx(found["x_probe_um"], abs=1e-4)
