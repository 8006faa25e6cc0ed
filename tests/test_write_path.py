"""The compensation write path against the real CNC protocols (OPC UA and Modbus TCP).

A CNC server from ``simulator.servers`` with a machine behind it that timestamps every
macro write as it lands (on the machine clock the gateway shares), Modbus TCP
temperature transmitters, a model fitted on synthetic runs, and the gateway's own
:class:`MachineLoop`, stepped cycle by cycle on a manual clock. Every slew check
here is made on the writes *as the CNC received them*, not on what the gateway
believes it did. Independent clients (asyncua, pymodbus) play the operator who
clears the macro at the CNC.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest
from asyncua import Client, ua
from pymodbus.client import AsyncModbusTcpClient

from drivers.clock import ManualClock
from drivers.register_codec import float32_to_registers
from gateway.config import ConfigError, MachineSection, load_config
from gateway.live.loop import MachineLoop
from gateway.live.record import CycleRecord
from gateway.wiring import build_buses, build_cnc, load_bank
from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.registry import make_model
from models.store import ModelStore
from simulator.link import ChannelReading, ChannelStatus, FixedLink, MachineSnapshot, RunMode
from simulator.servers.modbus_cnc import CncModbusServer, macro_register
from simulator.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from simulator.servers.opcua_cnc import CncOpcUaServer
from tests.ports import free_tcp_port
from tests.synthetic import stored_document, write_runs_csv

T = TypeVar("T")
HOST = "127.0.0.1"
MACRO = 500
SENSORS = [f"T{i}" for i in range(1, 8)]
CYCLE_S = 30.0
SLEW_UM_PER_MIN = 20.0  # 10 µm per 30 s cycle
COLD_C = 20.0
HOT_C = {**{name: COLD_C for name in SENSORS}, "T1": 30.0}  # ≈ 40 µm predicted
CNCS = ["opcua", "modbus"]


def run(body: Callable[[], Awaitable[T]], timeout_s: float = 120.0) -> T:
    async def bounded() -> T:
        return await asyncio.wait_for(body(), timeout_s)

    return asyncio.run(bounded())


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One MLR model on all seven sensors (error ≈ 4·ΔT1 − 2·ΔT6)."""
    return model_store(tmp_path_factory.mktemp("write-path"))


def model_store(folder: Path) -> Path:
    """A store in ``folder`` with one MLR model on all seven sensors."""
    prepared = prepare(load_runs(write_runs_csv(folder / "runs.csv")))
    model = make_model("mlr").fit(prepared.inputs, prepared.error_um)
    document = stored_document(prepared, model, "mlr-error_um-all")
    ModelStore(folder / "models").save(document)
    return folder / "models"


class ReceivingCnc(FixedLink):
    """The machine behind a CNC server: every macro write, timestamped as it lands."""

    def __init__(self, clock: ManualClock, held_mm: float = 0.0) -> None:
        super().__init__(
            MachineSnapshot(
                time_s=0.0,
                channels={},
                actual_speed_rpm=4000.0,
                commanded_speed_rpm=4000.0,
                run_mode=RunMode.AUTO,
                macros={MACRO: held_mm},
            )
        )
        self.clock = clock
        self.received: list[tuple[float, float]] = []  # (machine time, µm) of #500 writes

    def write_macro(self, number: int, value: float) -> None:
        super().write_macro(number, value)
        if number == MACRO:
            self.received.append((self.clock.now(), float(value) * 1000.0))

    @property
    def held_um(self) -> float:
        return self.macros[MACRO] * 1000.0


class SlowRelay:
    """A TCP hop in front of the transmitters whose next answer comes late.

    ``delay_next_s`` of machine time pass before the next answer is forwarded, as
    when a transmitter times out once and answers on the retry: the cycle goes on
    late, and so does its CNC write.
    """

    def __init__(self, clock: ManualClock, target: tuple[str, int]) -> None:
        self.clock = clock
        self.target = target
        self.delay_next_s = 0.0
        self._server: asyncio.Server | None = None

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._serve, HOST, 0)
        return int(self._server.sockets[0].getsockname()[1])

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(*self.target)

        async def pump(
            source: asyncio.StreamReader, sink: asyncio.StreamWriter, answers: bool
        ) -> None:
            try:
                while data := await source.read(4096):
                    if answers and self.delay_next_s:
                        self.clock.advance(self.delay_next_s)
                        self.delay_next_s = 0.0
                    sink.write(data)
                    await sink.drain()
            except ConnectionError:
                pass
            finally:
                sink.close()

        await asyncio.gather(pump(reader, up_writer, False), pump(up_reader, writer, True))


class Bench:
    """Transmitters, one CNC server (restartable on its port) and the gateway loop."""

    def __init__(self, cnc_kind: str, clock: ManualClock) -> None:
        self.cnc_kind = cnc_kind
        self.clock = clock
        self.temperatures = FixedLink(self._snapshot(HOT_C))
        self.transmitters = TransmitterServer(
            self.temperatures, [TransmitterDevice(1, SENSORS)], tcp=(HOST, free_tcp_port())
        )
        self.cnc_port = free_tcp_port()
        self.cnc = ReceivingCnc(clock)
        self.server: CncOpcUaServer | CncModbusServer | None = None
        self.relay: SlowRelay | None = None
        self.loop: MachineLoop | None = None
        self.records: list[CycleRecord] = []
        self._due = clock.now()  # start of the latest cycle, on the loop's schedule

    @staticmethod
    def _snapshot(temperatures_C: dict[str, float], faults: dict[str, ChannelStatus] | None = None):
        faults = faults or {}
        channels = {
            name: ChannelReading(math.nan, faults[name])
            if name in faults
            else ChannelReading(value)
            for name, value in temperatures_C.items()
        }
        return MachineSnapshot(0.0, channels, 0.0, 0.0, RunMode.STOP)

    def set_fault(self, sensor: str | None) -> None:
        """Open-circuit ``sensor`` (None: every sensor healthy again)."""
        faults = {} if sensor is None else {sensor: ChannelStatus.OPEN_CIRCUIT}
        self.temperatures.set_snapshot(self._snapshot(HOT_C, faults))

    def _new_server(self) -> CncOpcUaServer | CncModbusServer:
        if self.cnc_kind == "opcua":
            return CncOpcUaServer(self.cnc, port=self.cnc_port)
        return CncModbusServer(self.cnc, port=self.cnc_port)

    def machine(
        self, store: Path, transmitter_port: int, compensation: dict[str, Any]
    ) -> MachineSection:
        if self.cnc_kind == "opcua":
            link = {"opcua": {"endpoint": f"opc.tcp://{HOST}:{self.cnc_port}/cnc", "timeout_s": 1}}
        else:
            link = {"modbus": {"host": HOST, "port": self.cnc_port, "timeout_s": 0.5}}
        return MachineSection.model_validate(
            {
                "id": "wp-1",
                "cycle_s": CYCLE_S,
                "transmitters": [
                    {
                        "name": "bus1",
                        "tcp": {"host": HOST, "port": transmitter_port},
                        "timeout_s": 0.5,
                        "devices": [{"device_id": 1, "channels": SENSORS}],
                    }
                ],
                "sensors": {name: {"stale_s": 3 * CYCLE_S} for name in SENSORS},
                "cnc": link,
                "compensation": {
                    "macro": MACRO,
                    "unit": "mm",
                    "clamp_um": 50.0,
                    "slew_um_per_min": SLEW_UM_PER_MIN,
                    **compensation,
                },
                "models": {
                    "store": str(store),
                    "reference": {"mode": "fixed", "values_C": dict.fromkeys(SENSORS, COLD_C)},
                },
            }
        )

    async def start(self, store: Path, compensation: dict[str, Any], slow: bool) -> None:
        await self.transmitters.start()
        port = self.transmitters.address[1]
        if slow:
            self.relay = SlowRelay(self.clock, self.transmitters.address)
            port = await self.relay.start()
        self.server = self._new_server()
        await self.server.start()
        machine = self.machine(store, port, compensation)
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
        if self.relay is not None:
            await self.relay.stop()
        if self.server is not None:
            await self.server.stop()
        await self.transmitters.stop()

    async def cycle(self) -> CycleRecord:
        """One cycle: machine time moves on, the devices publish, the gateway runs once.

        Cycles start on the loop's schedule (every ``CYCLE_S`` from the first, as
        :meth:`MachineLoop.run` keeps them), so a late cycle is followed by one on time.
        """
        assert self.loop is not None
        self._due += CYCLE_S
        self.clock.advance(max(0.0, self._due - self.clock.now()))
        await self.transmitters.publish()
        if self.server is not None:
            await self.server.publish()
        record = await self.loop.run_cycle()
        self.records.append(record)
        return record

    async def cycles(self, n: int) -> list[CycleRecord]:
        return [await self.cycle() for _ in range(n)]

    async def stop_cnc(self) -> None:
        assert self.server is not None
        await self.server.stop()
        self.server = None

    async def start_cnc(self, held_mm: float) -> None:
        """A fresh CNC on the same port, holding ``held_mm`` in the macro (a restart)."""
        self.cnc = ReceivingCnc(self.clock, held_mm)
        self.server = self._new_server()
        await self.server.start()

    async def operator_writes(self, value_mm: float) -> None:
        """An independent client writes the macro at the CNC, as an operator would."""
        if self.cnc_kind == "opcua":
            assert isinstance(self.server, CncOpcUaServer)
            async with Client(self.server.endpoint, timeout=5) as client:
                node = client.get_node(ua.NodeId(f"Macro.{MACRO}", self.server.namespace_index))
                await node.write_value(ua.Variant(value_mm, ua.VariantType.Double))
        else:
            client = AsyncModbusTcpClient(HOST, port=self.cnc_port, timeout=2)
            assert await client.connect()
            try:
                words = list(float32_to_registers(value_mm))
                written = await client.write_registers(macro_register(MACRO), words, device_id=1)
                assert not written.isError(), written
            finally:
                client.close()
        assert self.cnc.held_um == pytest.approx(value_mm * 1000.0)


@contextlib.asynccontextmanager
async def bench(
    cnc_kind: str, store: Path, compensation: dict[str, Any] | None = None, slow: bool = False
) -> AsyncIterator[Bench]:
    bench = Bench(cnc_kind, ManualClock())
    try:
        await bench.start(store, compensation or {}, slow)
        yield bench
    finally:
        await bench.stop()


def assert_slew_as_received(
    received: list[tuple[float, float]], start: tuple[float, float] | None = None
) -> float:
    """Every write the CNC received moved at most the slew limit since the one before.

    ``start`` (time, µm) is what the CNC held before the first of them. Returns the
    largest step rate seen, µm/min.
    """
    pairs = ([start] if start else []) + received
    worst = 0.0
    for (t1, v1), (t2, v2) in itertools.pairwise(pairs):
        step_um = abs(v2 - v1)
        if step_um == 0.0:
            continue
        assert t2 > t1, (t1, t2)
        rate = 60.0 * step_um / (t2 - t1)
        assert rate <= SLEW_UM_PER_MIN + 1e-6, f"{v1} → {v2} µm in {t2 - t1:.2f} s: {rate} µm/min"
        worst = max(worst, rate)
    return worst


async def ramp_up(bench: Bench, cycles: int = 10) -> None:
    """Warm-up (sensors prove themselves good) and the ramp to the ≈ 40 µm prediction."""
    await bench.cycles(cycles)
    held = bench.cnc.held_um
    assert 35.0 < held <= 50.0, held
    assert bench.records[-1].applied_um == pytest.approx(held)


# --- (a) the macro cleared at the CNC ------------------------------------------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_macro_cleared_at_the_cnc_is_detected_counted_once_and_ramped_from(
    cnc_kind: str, store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    async def body() -> tuple[Bench, float, int]:
        async with bench(cnc_kind, store) as b:
            await ramp_up(b)
            before = len(b.cnc.received)
            believed = b.records[-1].applied_um
            await b.operator_writes(0.0)  # the operator clears #500
            cleared_s = b.clock.now()
            seen = await b.cycle()
            assert "external change" in seen.write_status
            assert seen.applied_um == 0.0  # what the CNC holds, not the old value
            assert believed is not None and believed > 35.0
            assert b.loop is not None and b.loop.external_changes == 1
            await b.cycles(8)
            assert b.loop.external_changes == 1  # counted once
            assert b.cnc.held_um > 35.0  # the compensation came back, at the slew limit
            worst = assert_slew_as_received(b.cnc.received[before + 1 :], (cleared_s, 0.0))
            return b, worst, before

    with caplog.at_level(logging.WARNING, logger="gateway.live.loop"):
        b, worst, before = run(body)
    logged = [r for r in caplog.records if "external change" in r.getMessage()]
    assert len(logged) == 1, [r.getMessage() for r in logged]
    after = [r for r in b.records if r.time_s > b.records[9].time_s]
    assert sum("external change" in r.write_status for r in after) == 1
    gateway_writes = b.cnc.received[before + 1 :]
    print(f"{cnc_kind}: cleared at {b.cnc.received[before][0]:.0f} s, then {gateway_writes}")
    assert gateway_writes and gateway_writes[0][1] <= 10.0 + 1e-9  # never a jump to 40 µm
    assert worst == pytest.approx(SLEW_UM_PER_MIN)


# --- (b) a CNC restart holding 0 -----------------------------------------------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_cnc_restart_holding_zero_ramps_up_from_zero(cnc_kind: str, store: Path) -> None:
    async def body() -> tuple[Bench, list[CycleRecord], float]:
        async with bench(cnc_kind, store) as b:
            await ramp_up(b)
            await b.stop_cnc()
            down = await b.cycles(3)
            assert all(not r.write_status.startswith("ok") for r in down)
            await b.start_cnc(held_mm=0.0)
            restarted_s = b.clock.now()
            after = await b.cycles(10)
            assert b.cnc.held_um > 35.0  # back at the prediction, by ramping
            assert b.loop is not None and b.loop.external_changes == 1
            assert_slew_as_received(b.cnc.received, (restarted_s, 0.0))
            return b, after, restarted_s

    b, after, _ = run(body)
    print(f"{cnc_kind}: after the restart the CNC received {b.cnc.received}")
    first_read = next(r for r in after if r.applied_um is not None)
    assert first_read.applied_um == 0.0 and "external change" in first_read.write_status
    values = [v for _, v in b.cnc.received]
    assert values[0] <= 10.0 + 1e-9  # the first write after the restart: one cycle of slew
    assert all(b2 - a2 <= 10.0 + 1e-9 for a2, b2 in itertools.pairwise(values))
    assert values == sorted(values)  # a ramp, never back and forth


# --- (c) a late write does not break the slew between writes as received -----------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_slew_as_received_holds_when_one_write_is_late(cnc_kind: str, store: Path) -> None:
    async def body() -> tuple[Bench, float]:
        async with bench(cnc_kind, store, {"deadband_um": 0.0}, slow=True) as b:
            assert b.relay is not None
            b.temperatures.set_snapshot(b._snapshot({**HOT_C, "T1": 32.0}))  # ≈ 48 µm
            await b.cycles(3)  # the sensors prove themselves, first write of 0, ramp starts
            b.relay.delay_next_s = 0.6  # one transmitter answer comes 0.6 s late
            late = await b.cycle()
            on_time = await b.cycle()
            assert "slew-limited" in late.write_status and "slew-limited" in on_time.write_status
            await b.cycles(4)
            received = b.cnc.received
            times = [t for t, _ in received]
            assert late.time_s + 0.6 in times and on_time.time_s in times  # as received
            return b, assert_slew_as_received(received)

    b, worst = run(body)
    print(f"{cnc_kind}: writes as received {b.cnc.received}; fastest {worst:.3f} µm/min")
    assert worst <= SLEW_UM_PER_MIN + 1e-6
    predicted = b.records[-1].predicted_um
    assert predicted is not None and b.cnc.held_um == pytest.approx(predicted, abs=0.6)


# --- (d) no prediction: hold, then ramp ----------------------------------------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_loss_of_prediction_holds_then_ramps_at_the_configured_rate(
    cnc_kind: str, store: Path
) -> None:
    hold_s, ramp_um_per_min = 90.0, 6.0  # 3 µm per 30 s cycle

    async def body() -> tuple[Bench, float, float, float]:
        settings = {"hold_on_loss_s": hold_s, "fallback_ramp_um_per_min": ramp_um_per_min}
        async with bench(cnc_kind, store, settings) as b:
            await ramp_up(b)
            held_um = b.cnc.held_um
            last_prediction_s = b.records[-1].time_s
            before = len(b.cnc.received)
            b.set_fault("T1")  # open circuit: no model without T1, no prediction
            # The hold, the ramp from what is held to 0, and two cycles more.
            ramp_s = held_um / ramp_um_per_min * 60.0
            records = await b.cycles(math.ceil((hold_s + ramp_s) / CYCLE_S) + 2)
            assert all(r.predicted_um is None for r in records)
            holding = [r for r in records if r.time_s - last_prediction_s < hold_s]
            assert holding and all("holding" in r.write_status for r in holding)
            assert b.cnc.held_um == 0.0
            writes = b.cnc.received[before:]
            return b, held_um, last_prediction_s, writes

    _b, held_um, last_prediction_s, writes = run(body)
    assert writes and writes[0][0] >= last_prediction_s + hold_s  # nothing moved in the hold
    pairs = [(last_prediction_s + hold_s, held_um), *writes]
    for (t1, v1), (t2, v2) in itertools.pairwise(pairs):
        assert v2 < v1 and v1 - v2 <= ramp_um_per_min * (t2 - t1) / 60.0 + 1e-9
    ramp_s = writes[-1][0] - (last_prediction_s + hold_s)
    expected_s = held_um / ramp_um_per_min * 60.0
    first_s = writes[0][0] - last_prediction_s
    print(f"{cnc_kind}: {held_um} µm held {first_s:.0f} s, then to 0 in {ramp_s:.0f} s: {writes}")
    assert expected_s <= ramp_s <= expected_s + CYCLE_S  # the configured rate, to a cycle


# --- (e) switched off: ramp to 0, or hold ---------------------------------------------------


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_disabled_with_ramp_goes_to_zero_at_the_slew_limit_then_stops(
    cnc_kind: str, store: Path
) -> None:
    async def body() -> tuple[Bench, int, float]:
        async with bench(cnc_kind, store, {"on_disable": "ramp"}) as b:
            await ramp_up(b)
            assert b.loop is not None
            before = len(b.cnc.received)
            held = b.cnc.held_um
            b.loop.compensation_enabled = False  # what the SCADA switch does
            await b.cycles(8)
            assert b.cnc.held_um == 0.0
            writes = b.cnc.received[before:]
            assert_slew_as_received(b.cnc.received[before - 1 :])  # from the last write on
            at_zero = len(b.cnc.received)
            await b.cycles(3)
            assert len(b.cnc.received) == at_zero  # at 0, the writes stop
            b.loop.compensation_enabled = True
            await b.cycles(6)
            assert_slew_as_received(b.cnc.received[at_zero - 1 :])
            return b, len(writes), held

    b, n_writes, held = run(body)
    print(f"{cnc_kind}: switched off at {held} µm: {n_writes} writes to 0")
    assert n_writes >= math.ceil(held / 10.6)  # ≤ 10 µm a cycle (+ the deadband): a ramp
    assert b.cnc.held_um > 35.0


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_disabled_with_hold_leaves_the_cnc_untouched(cnc_kind: str, store: Path) -> None:
    async def body() -> Bench:
        async with bench(cnc_kind, store, {"on_disable": "hold"}) as b:
            await ramp_up(b)
            assert b.loop is not None
            before = len(b.cnc.received)
            held = b.cnc.held_um
            b.loop.compensation_enabled = False
            b.temperatures.set_snapshot(b._snapshot({**HOT_C, "T1": 25.0}))  # ≈ 20 µm now
            records = await b.cycles(6)
            assert len(b.cnc.received) == before and b.cnc.held_um == held
            assert all(r.write_status.startswith("disabled") for r in records)
            assert all(r.applied_um == pytest.approx(held) for r in records)
            b.loop.compensation_enabled = True  # on again: from what the CNC holds, slowly
            resumed_s = b.records[-1].time_s
            await b.cycles(4)
            assert_slew_as_received(b.cnc.received[before:], (resumed_s, held))
            assert b.cnc.held_um < held
            return b

    run(body)


# --- the configuration of the write path ---------------------------------------------------

CONFIG = """\
machines:
  - id: vmc-1
    cycle_s: 30
    transmitters:
      - name: bus1
        tcp: {host: 127.0.0.1, port: 5020}
        devices:
          - {device_id: 1, channels: [T1]}
    cnc:
      modbus: {host: 127.0.0.1, port: 5021}
    compensation:
      slew_um_per_min: 20
      SETTING
    models:
      store: models
"""


def test_write_path_settings_and_their_defaults(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(CONFIG.replace("SETTING", "deadband_um: 0.5"), encoding="utf-8")
    defaults = load_config(path).machines[0].compensation
    assert (defaults.on_disable, defaults.hold_on_loss_s) == ("ramp", 60.0)
    assert defaults.limits().ramp_um_per_min == 20.0  # the fallback ramp: the slew rate
    setting = "hold_on_loss_s: 120\n      fallback_ramp_um_per_min: 5\n      on_disable: hold"
    path.write_text(CONFIG.replace("SETTING", setting), encoding="utf-8")
    section = load_config(path).machines[0].compensation
    assert section.on_disable == "hold"
    limits = section.limits()
    assert (limits.hold_on_loss_s, limits.ramp_um_per_min) == (120.0, 5.0)


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("on_disable: freeze", "on_disable: Input should be 'ramp' or 'hold'"),
        ("hold_on_loss_s: -1", "hold_on_loss_s: Input should be greater than or equal to 0"),
        (
            "hold_on_loss_s: .inf",
            "hold_on_loss_s: .inf is not a finite number; a finite value was expected",
        ),
        ("fallback_ramp_um_per_min: 0", "fallback_ramp_um_per_min: Input should be greater than 0"),
    ],
)
def test_bad_write_path_settings_are_refused_with_their_line(
    tmp_path: Path, setting: str, message: str
) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(CONFIG.replace("SETTING", setting), encoding="utf-8")
    with pytest.raises(ConfigError) as refused:
        load_config(path)
    assert str(refused.value) == f"{path}:13: machines[0].compensation.{message}"


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_a_spindle_turning_in_reverse_counts_by_its_magnitude(
    cnc_kind: str, store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A control that signs the actual speed by direction (M04) reports −4000 r/min; the
    bearings heat as at +4000, so the loop takes 4000, and says so once."""

    async def body() -> list[CycleRecord]:
        async with bench(cnc_kind, store) as b:
            forward = await b.cycles(2)
            b.cnc.set_snapshot(
                MachineSnapshot(0.0, {}, -4000.0, -4000.0, RunMode.AUTO, macros=dict(b.cnc.macros))
            )
            return [*forward, *await b.cycles(3)]

    with caplog.at_level(logging.INFO, logger="gateway.live.loop"):
        records = run(body)
    assert [r.speed_rpm for r in records] == [4000.0] * 5
    noted = [r.getMessage() for r in caplog.records if "negative spindle speed" in r.getMessage()]
    assert noted == [
        "wp-1: the CNC reports a negative spindle speed (-4000 r/min, turning in reverse); "
        "its magnitude is used"
    ]
