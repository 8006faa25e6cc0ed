"""A three-axis machine (Z, X, Y) compensated live against the real CNC protocols.

Modbus TCP temperature transmitters and a CNC server of ``simulator.servers`` (OPC UA,
or Modbus TCP) with a machine behind it that timestamps every macro write as it
lands, and the gateway's own :class:`MachineLoop`, stepped cycle by cycle on a manual
clock. Three models (:mod:`tests.axes_rig`), one per axis, each predicting its own
error column; every check is made on the writes as the CNC received them. Independent
clients (asyncua, pymodbus) play the operator who changes one axis's macro at the CNC.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest
from asyncua import Client, ua
from pymodbus.client import AsyncModbusTcpClient

from drivers.clock import ManualClock
from drivers.register_codec import float32_to_registers
from gateway.config import MachineSection
from gateway.live.loop import MachineLoop
from gateway.live.record import CycleRecord
from gateway.wiring import build_buses, build_cnc, load_bank
from simulator.link import ChannelReading, ChannelStatus, FixedLink, MachineSnapshot, RunMode
from simulator.servers.modbus_cnc import CncModbusServer, macro_register
from simulator.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from simulator.servers.opcua_cnc import CncOpcUaServer
from tests.axes_rig import axes_store
from tests.ports import free_tcp_port

T = TypeVar("T")
HOST = "127.0.0.1"
SENSORS = [f"T{i}" for i in range(1, 8)]
CYCLE_S = 30.0
COLD_C = 20.0
#: z ≈ 4·10 = 40 µm, x ≈ 1.5·10 = 15 µm (beyond X's clamp), y ≈ −1·10 = −10 µm
HOT_C = {**dict.fromkeys(SENSORS, COLD_C), "T1": 30.0, "T2": 30.0, "T3": 30.0}
HANDSHAKE = 510
ALIVE = 511
#: Each axis's section of compensation.axes: its own macro, unit, sign and limits.
AXES: dict[str, dict[str, Any]] = {
    "Z": {"macro": 500, "unit": "mm", "clamp_um": 50.0, "slew_um_per_min": 20.0},
    "X": {
        "macro": 502,
        "unit": "um",
        "sign": -1,
        "clamp_um": 12.0,
        "slew_um_per_min": 8.0,
        "hold_on_loss_s": 60.0,
        "fallback_ramp_um_per_min": 4.0,
    },
    "Y": {"macro": 503, "unit": "mm", "clamp_um": 30.0, "slew_um_per_min": 10.0},
}
TARGETS = {"Z": "z_um", "X": "x_um", "Y": "y_um"}
#: X's model needs T7, which Z's and Y's do without: losing T7 leaves X without a model.
MODEL_SENSORS = {"x_um": ["T2", "T7"], "z_um": SENSORS[:6], "y_um": SENSORS[:6]}
CNCS = ["opcua", "modbus"]


def run(body: Callable[[], Awaitable[T]], timeout_s: float = 180.0) -> T:
    async def bounded() -> T:
        return await asyncio.wait_for(body(), timeout_s)

    return asyncio.run(bounded())


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return axes_store(tmp_path_factory.mktemp("axes-live"), sensors=MODEL_SENSORS)


def to_um(axis: str, value_cnc: float) -> float:
    """A value in the CNC's unit and sign → the compensation it applies, µm."""
    section = AXES[axis]
    return value_cnc * (1000.0 if section["unit"] == "mm" else 1.0) * section.get("sign", 1)


class ReceivingCnc(FixedLink):
    """The machine behind a CNC server: every macro write, timestamped as it lands."""

    def __init__(self, clock: ManualClock) -> None:
        super().__init__(
            MachineSnapshot(
                time_s=0.0,
                channels={},
                actual_speed_rpm=4000.0,
                commanded_speed_rpm=4000.0,
                run_mode=RunMode.AUTO,
                macros={a["macro"]: 0.0 for a in AXES.values()},
            )
        )
        self.clock = clock
        self.received: dict[int, list[tuple[float, float]]] = {}  # macro → (time, value)
        self.refused: set[int] = set()  # macros the machine refuses to take (write-protected)

    def write_macro(self, number: int, value: float) -> None:
        if number in self.refused:  # the server answers the write with an error status
            raise ValueError(f"macro #{number} is write-protected")
        super().write_macro(number, value)
        self.received.setdefault(number, []).append((self.clock.now(), float(value)))

    def axis_um(self, axis: str) -> list[tuple[float, float]]:
        """The axis's writes as received, µm."""
        return [(t, to_um(axis, v)) for t, v in self.received.get(AXES[axis]["macro"], [])]

    def held_um(self, axis: str) -> float:
        return to_um(axis, self.macros[AXES[axis]["macro"]])


class Bench:
    """Transmitters, one CNC server and the gateway loop of a three-axis machine."""

    def __init__(self, cnc_kind: str, clock: ManualClock) -> None:
        self.cnc_kind = cnc_kind
        self.clock = clock
        self.temperatures = FixedLink(self._snapshot(HOT_C))
        self.transmitters = TransmitterServer(
            self.temperatures, [TransmitterDevice(1, SENSORS)], tcp=(HOST, free_tcp_port())
        )
        self.cnc_port = free_tcp_port()
        self.cnc = ReceivingCnc(clock)
        self.server: CncOpcUaServer | CncModbusServer = (
            CncOpcUaServer(self.cnc, port=self.cnc_port)
            if cnc_kind == "opcua"
            else CncModbusServer(self.cnc, port=self.cnc_port)
        )
        self.loop: MachineLoop | None = None
        self.records: list[CycleRecord] = []
        self._due = clock.now()

    @staticmethod
    def _snapshot(
        temperatures_C: dict[str, float], faults: dict[str, ChannelStatus] | None = None
    ) -> MachineSnapshot:
        faults = faults or {}
        channels = {
            name: ChannelReading(math.nan, faults[name]) if name in faults else ChannelReading(v)
            for name, v in temperatures_C.items()
        }
        return MachineSnapshot(0.0, channels, 0.0, 0.0, RunMode.STOP)

    def set_temperatures(self, temperatures_C: dict[str, float], fault: str | None = None) -> None:
        faults = {} if fault is None else {fault: ChannelStatus.OPEN_CIRCUIT}
        self.temperatures.set_snapshot(self._snapshot(temperatures_C, faults))

    def machine(self, store: Path) -> MachineSection:
        if self.cnc_kind == "opcua":
            link = {"opcua": {"endpoint": f"opc.tcp://{HOST}:{self.cnc_port}/cnc", "timeout_s": 1}}
        else:
            link = {"modbus": {"host": HOST, "port": self.cnc_port, "timeout_s": 0.5}}
        axes = {
            name: {**section, "fallback_model": f"mlr-{TARGETS[name]}-all"}
            for name, section in AXES.items()
        }
        return MachineSection.model_validate(
            {
                "id": "xyz-1",
                "cycle_s": CYCLE_S,
                "transmitters": [
                    {
                        "name": "bus1",
                        "tcp": {"host": HOST, "port": self.transmitters.address[1]},
                        "timeout_s": 0.5,
                        "devices": [{"device_id": 1, "channels": SENSORS}],
                    }
                ],
                "sensors": {name: {"stale_s": 3 * CYCLE_S} for name in SENSORS},
                "cnc": link,
                "compensation": {"handshake_macro": HANDSHAKE, "alive_macro": ALIVE, "axes": axes},
                "models": {
                    "store": str(store),
                    "reference": {"mode": "fixed", "values_C": dict.fromkeys(SENSORS, COLD_C)},
                },
            }
        )

    async def start(self, store: Path) -> None:
        await self.transmitters.start()
        await self.server.start()
        machine = self.machine(store)
        self.loop = MachineLoop(
            machine,
            self.clock,
            build_buses(machine),
            build_cnc(machine, self.clock),
            load_bank(machine),
        )

    async def stop(self) -> None:
        if self.loop is not None:
            await self.loop.close()
        await self.server.stop()
        await self.transmitters.stop()

    async def cycle(self) -> CycleRecord:
        assert self.loop is not None
        self._due += CYCLE_S
        self.clock.advance(max(0.0, self._due - self.clock.now()))
        await self.transmitters.publish()
        await self.server.publish()
        record = await self.loop.run_cycle()
        self.records.append(record)
        return record

    async def cycles(self, n: int) -> list[CycleRecord]:
        return [await self.cycle() for _ in range(n)]

    async def operator_writes(self, axis: str, value_cnc: float) -> None:
        """An independent client writes one axis's macro at the CNC, as an operator would."""
        macro = AXES[axis]["macro"]
        if isinstance(self.server, CncOpcUaServer):
            async with Client(self.server.endpoint, timeout=5) as client:
                node = client.get_node(ua.NodeId(f"Macro.{macro}", self.server.namespace_index))
                await node.write_value(ua.Variant(value_cnc, ua.VariantType.Double))
        else:
            client = AsyncModbusTcpClient(HOST, port=self.cnc_port, timeout=2)
            assert await client.connect()
            try:
                words = list(float32_to_registers(value_cnc))
                written = await client.write_registers(macro_register(macro), words, device_id=1)
                assert not written.isError(), written
            finally:
                client.close()
        assert self.cnc.macros[macro] == pytest.approx(value_cnc)


@contextlib.asynccontextmanager
async def bench(cnc_kind: str, store: Path) -> AsyncIterator[Bench]:
    b = Bench(cnc_kind, ManualClock())
    try:
        await b.start(store)
        yield b
    finally:
        await b.stop()


def assert_within_limits(received: list[tuple[float, float]], axis: str, start_um: float) -> None:
    """Every write of ``axis`` the CNC received is inside its clamp and moved at most its
    slew limit since the one before (``start_um``: what the macro held before them)."""
    section = AXES[axis]
    clamp, slew = section["clamp_um"], section["slew_um_per_min"]
    assert all(abs(v) <= clamp + 1e-6 for _, v in received), (axis, received)
    pairs = [(received[0][0] - CYCLE_S, start_um), *received]
    for (t1, v1), (t2, v2) in itertools.pairwise(pairs):
        assert abs(v2 - v1) <= slew * (t2 - t1) / 60.0 + 1e-6, (axis, (t1, v1), (t2, v2))


def handshake_bumps_per_cycle(b: Bench) -> dict[float, int]:
    """How many handshake writes the CNC received at each cycle's time."""
    times = [t for t, _ in b.cnc.received.get(HANDSHAKE, [])]
    return {t: times.count(t) for t in times}


def assert_one_handshake_per_cycle_with_writes(b: Bench) -> None:
    """One bump in each cycle with a confirmed write of any axis, none in the others."""
    with_writes = [
        r.time_s for r in b.records if any(a.write_status.startswith("ok") for a in r.axes.values())
    ]
    assert with_writes
    assert handshake_bumps_per_cycle(b) == dict.fromkeys(with_writes, 1)
    assert b.loop is not None and b.loop.handshake == len(with_writes)
    assert b.cnc.macros[HANDSHAKE] == float(len(with_writes))


# --- (a) every axis follows its own prediction within its own limits --------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_three_axes_each_follow_their_own_prediction_within_their_own_limits(
    cnc_kind: str, store: Path
) -> None:
    async def body() -> Bench:
        async with bench(cnc_kind, store) as b:
            await b.cycles(12)
            return b

    b = run(body)
    last = b.records[-1]
    assert list(last.axes) == ["Z", "X", "Y"]
    assert {a: r.model_id for a, r in last.axes.items()} == {
        a: f"mlr-{TARGETS[a]}-all" for a in AXES
    }
    predicted = {a: r.predicted_um for a, r in last.axes.items()}
    print(f"{cnc_kind}: predicted {predicted}, held {[b.cnc.held_um(a) for a in AXES]} µm")
    assert predicted["Z"] == pytest.approx(40.0, abs=2.0)
    assert predicted["X"] == pytest.approx(15.0, abs=1.5)
    assert predicted["Y"] == pytest.approx(-10.0, abs=1.5)
    # Each macro holds its own axis's prediction, within that axis's clamp.
    assert b.cnc.held_um("Z") == pytest.approx(predicted["Z"], abs=0.5)
    assert b.cnc.held_um("X") == pytest.approx(AXES["X"]["clamp_um"])  # 15 µm, clamped
    assert b.cnc.macros[502] == pytest.approx(-12.0)  # µm, sign −1
    assert b.cnc.held_um("Y") == pytest.approx(predicted["Y"], abs=0.5)
    for axis in AXES:
        received = b.cnc.axis_um(axis)
        assert len(received) >= 2, (axis, received)
        assert_within_limits(received, axis, 0.0)
        assert last.axes[axis].applied_um == pytest.approx(b.cnc.held_um(axis))
    # The record's own fields are the first axis's.
    z = last.axes["Z"]
    assert (last.model_id, last.predicted_um, last.applied_um, last.write_status) == (
        z.model_id,
        z.predicted_um,
        z.applied_um,
        z.write_status,
    )
    assert_one_handshake_per_cycle_with_writes(b)
    assert len(b.cnc.received[ALIVE]) == len(b.records)  # one alive count per cycle


# --- (b) one axis loses its model; the others keep compensating --------------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_an_axis_without_a_model_holds_then_ramps_while_the_others_write(
    cnc_kind: str, store: Path
) -> None:
    async def body() -> tuple[Bench, int, float]:
        async with bench(cnc_kind, store) as b:
            await b.cycles(10)
            assert b.cnc.held_um("X") == pytest.approx(12.0)
            lost_s = b.records[-1].time_s  # X's last prediction
            # T7 open: X's only model needs it. Z and Y move on to new predictions, warming
            # in steps the prediction rate bound takes as heat (≤ 2 µm a cycle).
            start = len(b.records)
            for step in range(1, 5):
                warmer = {"T1": 30.0 + 0.5 * step, "T3": 30.0 + 0.5 * step}
                b.set_temperatures({**HOT_C, **warmer}, fault="T7")
                await b.cycle()
            await b.cycles(6)
            return b, start, lost_s

    b, start, lost_s = run(body)
    after = b.records[start:]
    assert all(r.quality["T7"] == "bad" for r in after)
    assert all(r.axes["X"].model_id is None and r.axes["X"].predicted_um is None for r in after)
    assert all(r.axes["Z"].model_id == "mlr-z_um-all" for r in after)
    x_writes = [(t, v) for t, v in b.cnc.axis_um("X") if t > lost_s]
    print(f"{cnc_kind}: X after the loss {x_writes}")
    # Held for hold_on_loss_s after its last prediction, then ramped at the fallback ramp.
    assert "no prediction: holding for 60 s" in after[0].axes["X"].write_status
    assert after[0].axes["X"].applied_um == pytest.approx(12.0)
    assert x_writes and all(t - lost_s >= AXES["X"]["hold_on_loss_s"] for t, _ in x_writes)
    ramp_um = AXES["X"]["fallback_ramp_um_per_min"] * CYCLE_S / 60.0
    values = [12.0] + [v for _, v in x_writes]
    assert all(
        0.0 <= v2 < v1 and v1 - v2 <= ramp_um + 1e-6 for v1, v2 in itertools.pairwise(values)
    )
    assert values[-1] < 12.0 - 3 * ramp_um + 1e-6  # it kept ramping
    # Z and Y wrote their new predictions at their own slew limits meanwhile.
    for axis, moved in (("Z", 8.0), ("Y", -2.0)):
        ok = [r for r in after if r.axes[axis].write_status.startswith("ok")]
        assert ok, axis
        assert_within_limits(b.cnc.axis_um(axis), axis, 0.0)
        assert b.cnc.held_um(axis) == pytest.approx(after[-1].axes[axis].predicted_um, abs=0.5)
        assert after[-1].axes[axis].predicted_um == pytest.approx(
            b.records[start - 1].axes[axis].predicted_um + moved, abs=1.5
        )
    assert b.loop is not None
    assert [a.failed_writes for a in b.loop.axes] == [0, 0, 0]
    assert_one_handshake_per_cycle_with_writes(b)


# --- (b') one axis's writes fail; the others keep compensating -----------------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_an_axis_whose_writes_fail_holds_while_the_others_write(cnc_kind: str, store: Path) -> None:
    async def body() -> tuple[Bench, list[CycleRecord], list[CycleRecord]]:
        async with bench(cnc_kind, store) as b:
            b.cnc.refused.add(AXES["X"]["macro"])  # X's macro write-protected at the CNC
            refused = await b.cycles(8)
            assert b.loop is not None
            assert [a.failed_writes for a in b.loop.axes] == [0, len(refused), 0]
            assert b.loop.failed_writes == len(refused)  # the machine total
            b.cnc.refused.clear()
            return b, refused, await b.cycles(6)

    b, refused, after = run(body)
    assert all(r.axes["X"].write_status.startswith("write failed") for r in refused)
    assert all(r.axes["X"].applied_um == 0.0 for r in refused)  # never moved by a failure
    assert 502 not in b.cnc.received or all(t > refused[-1].time_s for t, _ in b.cnc.axis_um("X"))
    # Z and Y compensated meanwhile, within their own limits.
    assert b.cnc.held_um("Z") == pytest.approx(refused[-1].axes["Z"].predicted_um, abs=0.5)
    assert b.cnc.held_um("Y") == pytest.approx(refused[-1].axes["Y"].predicted_um, abs=0.5)
    for axis in ("Z", "Y"):
        assert_within_limits(b.cnc.axis_um(axis), axis, 0.0)
    # Once the CNC takes it again, X ramps from what the CNC holds at its own slew limit:
    # its first step one cycle's slew (8 µm/min for 30 s) plus at most the deadband and
    # one CNC step the budget keeps after a hold (gateway/live/writeback.py).
    x_writes = b.cnc.axis_um("X")
    assert x_writes[0][0] == after[0].time_s
    assert 4.0 <= x_writes[0][1] <= 4.0 + 0.5 + 1e-4 + 1e-9
    assert_within_limits(x_writes, "X", x_writes[0][1])
    assert b.cnc.held_um("X") == pytest.approx(12.0)
    assert_one_handshake_per_cycle_with_writes(b)


# --- (c) an operator changes one axis's macro at the CNC ---------------------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_an_operator_change_of_one_axis_is_that_axis_s_alone(cnc_kind: str, store: Path) -> None:
    async def body() -> tuple[Bench, CycleRecord, float]:
        async with bench(cnc_kind, store) as b:
            await b.cycles(10)
            assert b.cnc.held_um("Y") == pytest.approx(-10.0, abs=2.0)
            await b.operator_writes("Y", 0.0)  # the operator clears Y's #503
            cleared_s = b.clock.now()
            seen = await b.cycle()
            await b.cycles(4)
            return b, seen, cleared_s

    b, seen, cleared_s = run(body)
    assert b.loop is not None
    assert {a.name: a.external_changes for a in b.loop.axes} == {"Z": 0, "X": 0, "Y": 1}
    assert b.loop.external_changes == 1
    assert "external change: CNC macro #503" in seen.axes["Y"].write_status
    assert "external change" not in seen.axes["Z"].write_status + seen.axes["X"].write_status
    # Y re-seeded from the CNC's 0 and ramps back at its own slew limit.
    assert seen.axes["Y"].applied_um == 0.0  # what the CNC holds, not the old value
    assert seen.axes["Z"].applied_um == pytest.approx(b.cnc.held_um("Z"))
    later = [(t, v) for t, v in b.cnc.axis_um("Y") if t > cleared_s]
    assert later[0][1] == pytest.approx(-5.0)  # from 0, one cycle of 10 µm/min
    assert_within_limits(later, "Y", 0.0)
    assert b.cnc.held_um("Y") == pytest.approx(b.records[-1].axes["Y"].predicted_um, abs=0.5)
    assert all("external change" not in r.axes["Y"].write_status for r in b.records[-4:])
