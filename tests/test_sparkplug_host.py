"""The gateway as a Sparkplug B edge node, seen by a host nobody here wrote.

A real Mosquitto 2 (TLS, password file) on loopback; Eclipse Tahu's JavaScript payload
library decodes every message in tests/node/sparkplug_host.mjs and checks the sequence
numbers; three simulated machines over Modbus TCP, the gateway on wall time.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import time
from pathlib import Path
from typing import Any

import pytest

from drivers.clock import AcceleratedClock, Clock, WallClock
from gateway.config import GatewayConfig
from gateway.live.record import CycleRecord
from gateway.sparkplug.metrics import PROMOTE
from gateway.wiring import Gateway
from tests import gateway_rig as rig
from tests.mqtt_broker import PASSWORD, USER, Broker, mosquitto
from tests.sparkplug_host import TahuHost

GROUP, NODE, HOST = "plant1", "edge1", "scada"
MACHINES = ("m1", "m2", "m3")
CYCLE_S = 0.2


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("sparkplug"))


def gateway_config(
    tmp_path: Path,
    broker: Broker,
    plants: list[Any],
    store: Path,
    commands: dict[str, bool],
    cycle_s: float = CYCLE_S,
    state_dir: Path | None = None,
    qos: int | None = None,
) -> GatewayConfig:
    return GatewayConfig.model_validate(
        {
            "state_dir": str(state_dir or tmp_path / "state"),
            "logging": {"local_store": str((state_dir or tmp_path) / "points.sqlite")},
            "machines": [
                rig.machine_entry(m, p, store, cycle_s=cycle_s)
                for m, p in zip(MACHINES, plants, strict=True)
            ],
            "sparkplug": {
                "brokers": [broker.url],
                "group_id": GROUP,
                "edge_node_id": NODE,
                "primary_host_id": HOST,
                "username": USER,
                "password_env": "SPB_TEST_PASSWORD",
                "ca_file": str(broker.ca_file),
                "startup_delay_max_s": 0.5,
                "reconnect_max_s": 2.0,
                "buffer_path": str(tmp_path / "spb.sqlite"),
                "commands": commands,
                **({} if qos is None else {"qos": qos}),
            },
        }
    )


def cycles_of(host: TahuHost, device: str) -> list[int]:
    """The cycle counter of every DDATA of ``device``, in arrival order."""
    return [
        m["value"]
        for e in host.messages("DDATA", device)
        for m in e["metrics"]
        if m["name"] == "Health/cycles"
    ]


def assert_every_cycle_once_in_order(host: TahuHost, records: list[CycleRecord]) -> None:
    for machine in MACHINES:
        seen = cycles_of(host, machine)
        ran = len([r for r in records if r.machine == machine])
        assert seen == list(range(seen[0], seen[0] + len(seen))), f"{machine}: gap or repeat"
        assert seen[0] == 1 and len(seen) >= ran - 1, (machine, len(seen), ran)


def assert_on_time(records: list[CycleRecord], restarted: tuple[str, ...] = ()) -> None:
    """Every cycle ran: as many as the run's length allows (5 % for a loaded 2-core host),
    and no stall longer than a few cycles; a ``restarted`` machine's loop was down for
    its supervisor's back-off (0.5 s + 20 %) once."""
    for machine in MACHINES:
        times = [r.time_s for r in records if r.machine == machine]
        steps = sorted(b - a for a, b in itertools.pairwise(times))
        if machine in restarted:
            assert steps[-1] < 4 * CYCLE_S + 0.6, (machine, steps[-1])
            steps.pop()
        assert steps[-1] < 4 * CYCLE_S, (machine, steps[-1])
        down_s = 0.6 if machine in restarted else 0.0
        assert len(times) >= 0.95 * ((times[-1] - times[0] - down_s) / CYCLE_S + 1), (
            machine,
            len(times),
        )


async def fail_one_cycle(run: Run, machine: str) -> None:
    """``machine``'s loop raises once: DDEATH, its supervisor's restart, DBIRTH, data."""
    loop = run.gateway._loop_of(machine)
    real_cycle, left = loop.run_cycle, [1]

    async def failing_cycle() -> CycleRecord:
        if left[0]:
            left[0] -= 1
            raise RuntimeError("a fault injected into the cycle")
        return await real_cycle()

    births = len(run.host.messages("DBIRTH", machine))
    loop.run_cycle = failing_cycle  # type: ignore[method-assign]
    await run.host.wait(lambda: len(run.host.messages("DDEATH", machine)) == 1, 10, "DDEATH")
    # From the death itself: on a busy machine the birth (and data) may have come in by the
    # time the wait returns, and counting from there would miss them.
    dead_at = 1 + next(
        i
        for i, e in enumerate(run.host.messages())
        if e["kind"] == "DDEATH" and e["device"] == machine
    )
    await run.host.wait(
        lambda: len(run.host.messages("DBIRTH", machine)) == births + 1, 10, "DBIRTH again"
    )
    cycles = len(cycles_of(run.host, machine))
    await run.host.wait(lambda: len(cycles_of(run.host, machine)) > cycles + 3, 10, "data again")
    after = [e["kind"] for e in run.host.messages()[dead_at:] if e["device"] == machine]
    assert after[0] == "DBIRTH", after[:3]  # nothing of the machine between death and birth
    assert run.gateway.supervisors[machine].restarts == 1


class Run:
    """Broker, host, plants and a running gateway for one scenario: on wall time, or with
    ``speedup`` on the simulator's accelerated clock (machine time ``speedup`` × faster,
    from now, so the points carry Unix-like machine-time stamps)."""

    def __init__(
        self,
        tmp_path: Path,
        store: Path,
        commands: dict[str, bool],
        cycle_s: float = CYCLE_S,
        speedup: float | None = None,
        state_dir: Path | None = None,
        qos: int | None = None,
    ) -> None:
        self.tmp_path, self.store, self.commands = tmp_path, store, commands
        self.cycle_s, self.speedup, self.state_dir = cycle_s, speedup, state_dir
        self.qos = qos
        self.records: list[CycleRecord] = []
        self.late_s: dict[str, list[float]] = {m: [] for m in MACHINES}  # machine time
        self.due_s: dict[str, list[float]] = {m: [] for m in MACHINES}

    async def __aenter__(self) -> Run:
        self.broker_cm = mosquitto(self.tmp_path / "broker")
        self.broker = self.broker_cm.__enter__()
        self.host = TahuHost(self.broker, GROUP, HOST)
        await self.host.wait(lambda: any(e["event"] == "online" for e in self.host.snapshot()),
                             20, "the host's STATE")  # fmt: skip
        clock: Clock = (
            WallClock()
            if self.speedup is None
            else AcceleratedClock(self.speedup, origin_s=time.time())
        )
        self.plants = [rig.plant(clock, seed=i, cnc=("modbus",)) for i in range(len(MACHINES))]
        for plant in self.plants:
            await plant.start()
        config = gateway_config(
            self.tmp_path,
            self.broker,
            self.plants,
            self.store,
            self.commands,
            self.cycle_s,
            self.state_dir,
            self.qos,
        )
        self.gateway = Gateway(config, clock=clock, sinks=[self.records.append, self._lateness])
        self.stop = asyncio.Event()
        self.task = asyncio.create_task(self.gateway.run(self.stop))
        return self

    async def stop_gateway(self) -> None:
        self.stop.set()
        await asyncio.wait_for(self.task, 20)

    async def __aexit__(self, *exc: object) -> None:
        if not self.task.done():
            await self.stop_gateway()
        for plant in self.plants:
            await plant.stop()
        self.host.close()
        self.broker_cm.__exit__(None, None, None)

    def _lateness(self, record: CycleRecord) -> None:
        """The scheduler's due time of the cycle and how late it started (machine s)."""
        due_s = self.gateway._loop_of(record.machine).due_s
        self.due_s[record.machine].append(due_s)
        self.late_s[record.machine].append(record.time_s - due_s)

    def alias(self, device: str, name: str) -> int:
        birth = self.host.messages("DBIRTH", device)[0]
        return next(m["alias"] for m in birth["metrics"] if m["name"] == name)

    def enabled(self, machine: str) -> bool:
        return self.gateway._loop_of(machine).compensation_enabled


def dcmd(run: Run, device: str, metric: dict[str, Any], timestamp: int, seq: int) -> None:
    run.host.send(op="dcmd", node=NODE, device=device, metrics=[metric], timestamp=timestamp,
                  seq=seq)  # fmt: skip


async def settle(run: Run, sent_before: int) -> None:
    """Wait until the host has sent one more command and the node had time to act."""
    await run.host.wait(
        lambda: len([e for e in run.host.snapshot() if e["event"] == "sent"]) > sent_before,
        10,
        "the command sent",
    )
    await asyncio.sleep(1.0)


def sent_count(run: Run) -> int:
    return len([e for e in run.host.snapshot() if e["event"] == "sent"])


def bd_seq_of(message: dict[str, Any]) -> int:
    """The bdSeq of an NBIRTH or NDEATH, found by the name the node sent (not the alias)."""
    return next(m["value"] for m in message["metrics"] if m["sentName"] == "bdSeq")


def logged(caplog: pytest.LogCaptureFixture, *parts: str) -> list[str]:
    """The log lines that contain every one of ``parts``."""
    lines = [r.getMessage() for r in caplog.records]
    return [line for line in lines if all(p in line for p in parts)]


def assert_spec_qos(host: TahuHost) -> None:
    """Sparkplug 3.0: births, data and device deaths at QoS 0, NDEATH at QoS 1, none
    retained (the host subscribes at QoS 1, so it receives each at the QoS it was sent)."""
    messages = host.messages()
    kinds = {e["kind"] for e in messages}
    assert {"NBIRTH", "DBIRTH", "DDATA", "NDATA", "DDEATH", "NDEATH"} <= kinds, kinds
    wrong = [(e["kind"], e["qos"]) for e in messages if e["qos"] != (e["kind"] == "NDEATH")]
    assert not wrong, wrong[:5]
    assert not [e for e in messages if e["retain"]]


def assert_node_data(host: TahuHost) -> None:
    """The node's own counters: declared in NBIRTH by name, sent in NDATA by alias when
    they change (the host names them from the NBIRTH); the published count grows."""
    birth = {m["sentName"]: m for m in host.messages("NBIRTH")[0]["metrics"]}
    for key in ("sparkplug_published", "sparkplug_backlog", "forwarder_backlog"):
        assert birth[f"Health/{key}"]["type"] == "UInt64", birth.keys()
    published = [
        m["value"]
        for e in host.messages("NDATA")
        for m in e["metrics"]
        if m["name"] == "Health/sparkplug_published"
    ]
    assert len(published) >= 3 and published == sorted(published) and published[-1] > 0
    assert not [m for e in host.messages("NDATA") for m in e["metrics"] if m["sentName"]]


async def promote_unknown_proposal(
    run: Run, allowed: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """A promote DCMD reaches the gateway's promotion (the SCADA method's rules) only when
    ``promote_proposal`` is on; there it is refused for an unknown proposal id."""
    node = run.gateway.sparkplug
    assert node is not None
    refused, n = node.commands.refused, sent_count(run)
    metric = {"name": PROMOTE, "type": "String", "value": "no-such-proposal"}
    dcmd(run, "m1", metric, 6000, 6)
    await settle(run, n)
    assert node.commands.refused == refused + 1
    said = [r.getMessage() for r in caplog.records if "Promote Proposal" in r.getMessage()]
    if allowed:
        assert any("refused by the gateway" in m and "no-such-proposal" in m for m in said), said
    else:
        assert any("not allowed by sparkplug.commands" in m for m in said), said


@pytest.mark.parametrize("allowed", [True, False])
def test_tahu_host_decodes_births_data_rebirth_and_commands(
    tmp_path: Path,
    store: Path,
    allowed: bool,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    monkeypatch.setenv("SPB_TEST_PASSWORD", PASSWORD)

    async def scenario() -> None:
        commands = {"set_compensation": allowed, "promote_proposal": allowed}
        async with Run(tmp_path, store, commands) as run:
            host = run.host
            await host.wait(
                lambda: all(len(cycles_of(host, m)) >= 5 for m in MACHINES), 60, "5 DDATA each"
            )
            births = host.messages("NBIRTH")
            assert len(births) == 1 and births[0]["seq"] == 0
            bd_seq = bd_seq_of(births[0])
            rebirth = [m for m in births[0]["metrics"] if m["sentName"] == "Node Control/Rebirth"]
            assert rebirth[0]["type"] == "Boolean" and rebirth[0].get("alias") is None
            dbirth = host.messages("DBIRTH", "m1")[0]
            units = {m["name"]: m.get("unit") for m in dbirth["metrics"]}
            assert units["Temperature/T1"] == "°C" and units["Spindle/Speed"] == "r/min"
            assert units["Prediction"] == "µm"
            types = {m["name"]: m["type"] for m in dbirth["metrics"]}
            assert types["Compensation/Enabled"] == "Boolean" and types["Regime"] == "String"

            host.send(op="rebirth", node=NODE)
            await host.wait(lambda: len(host.messages("NBIRTH")) == 2, 10, "NBIRTH after rebirth")
            await host.wait(
                lambda: all(len(host.messages("DBIRTH", m)) == 2 for m in MACHINES), 10, "DBIRTHs"
            )
            again = host.messages("NBIRTH")[1]
            assert bd_seq_of(again) == bd_seq

            enabled = run.alias("m2", "Compensation/Enabled")
            assert run.enabled("m2")
            n = sent_count(run)
            dcmd(run, "m2", {"alias": enabled, "type": "Boolean", "value": False}, 1000, 1)
            await settle(run, n)
            assert run.enabled("m2") is (not allowed)
            assert run.enabled("m1") and run.enabled("m3")
            assert bool(logged(caplog, "compensation disabled from Sparkplug host")) is allowed
            assert not logged(caplog, "from SCADA")
            accepted = run.gateway.sparkplug.commands.accepted  # type: ignore[union-attr]
            assert accepted == (2 if allowed else 1)  # the rebirth, and the DCMD if allowed
            if allowed:
                n = sent_count(run)
                dcmd(run, "m2", {"alias": enabled, "type": "Boolean", "value": True}, 2000, 2)
                await settle(run, n)
                assert run.enabled("m2")
            refused = run.gateway.sparkplug.commands.refused  # type: ignore[union-attr]
            bad = [
                ({"alias": enabled, "type": "String", "value": "false"}, 3000, 3),  # datatype
                ({"alias": 987654, "type": "Boolean", "value": False}, 4000, 4),  # alias
                ({"alias": enabled, "type": "Boolean", "value": False}, 1000, 1),  # replay
                ({"name": "Compensation/Applied", "type": "Double", "value": 1000.0}, 5000, 5),
            ]
            for metric, timestamp, seq in bad:
                n = sent_count(run)
                dcmd(run, "m2", metric, timestamp, seq)
                await settle(run, n)
            n = sent_count(run)
            host.send(op="raw", topic=f"spBv1.0/{GROUP}/DCMD/{NODE}/m2", hex="ffff0a01")
            await settle(run, n)
            node = run.gateway.sparkplug
            assert node is not None
            assert node.commands.refused == refused + 5
            assert run.enabled("m2")  # nothing refused was acted on
            said = logged(caplog, "Compensation/Applied")
            assert len(said) == 1 and "is read-only" in said[0], said
            assert "Compensation/Enabled (Boolean)" in said[0], said
            await promote_unknown_proposal(run, allowed, caplog)
            if not allowed:  # one parametrization is enough for a loop's restart
                await fail_one_cycle(run, "m3")
            await run.stop_gateway()
            await host.wait(lambda: len(host.messages("NDEATH")) == 1, 10, "NDEATH at the stop")
            assert {e["device"] for e in host.messages("DDEATH")} == set(MACHINES)
            death = host.messages("NDEATH")[0]
            assert bd_seq_of(death) == bd_seq and death["seq"] is None
            assert [m["type"] for m in death["metrics"]] == ["Int64"]

        events = host.snapshot()
        assert not [e for e in events if e["event"] == "undecodable"]
        assert not [e for e in events if e["event"] == "message" and e["gap"]]
        assert_every_cycle_once_in_order(host, run.records)
        assert_on_time(run.records, restarted=() if allowed else ("m3",))
        assert_spec_qos(host)
        assert_node_data(host)
        assert len(host.messages("DDEATH", "m3")) == (1 if allowed else 2)  # + the stop's

    asyncio.run(scenario())


def test_primary_host_state_offline_disconnects_and_old_or_malformed_state_is_ignored(
    tmp_path: Path, store: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Sparkplug 3.0 on the primary host's STATE, seen from the independent host: a
    malformed STATE is ignored (logged) and data goes on; a valid ``offline`` makes the
    node publish NDEATH and disconnect, then connect again (a new bdSeq) and wait; an
    ``online`` older than that ``offline`` is ignored; the real ``online`` brings births."""
    monkeypatch.setenv("SPB_TEST_PASSWORD", PASSWORD)
    topic = f"spBv1.0/STATE/{HOST}"

    async def scenario() -> None:
        async with Run(tmp_path, store, {}) as run:
            host, node = run.host, run.gateway.sparkplug
            assert node is not None
            await host.wait(
                lambda: all(len(cycles_of(host, m)) >= 3 for m in MACHINES), 60, "3 DDATA each"
            )
            bd_seq = bd_seq_of(host.messages("NBIRTH")[0])

            host.send(op="rawstate", text='{"online": "yes"}')
            await host.wait(lambda: bool(logged(caplog, topic, "ignored")), 10, "the warning")
            seen = {m: len(cycles_of(host, m)) for m in MACHINES}
            await host.wait(
                lambda: all(len(cycles_of(host, m)) >= seen[m] + 5 for m in MACHINES),
                20,
                "data going on after a malformed STATE",
            )
            said = logged(caplog, topic, "ignored")
            assert "online is 'yes', not a boolean" in said[0], said
            assert node.sessions == 1 and host.count("NDEATH") == 0

            host.send(op="state", online=False)
            await host.wait(lambda: host.count("NDEATH") == 1, 10, "NDEATH at the host's offline")
            assert bd_seq_of(host.messages("NDEATH")[0]) == bd_seq
            await host.wait(
                lambda: node.sessions == 2 and node.link is not None, 10, "a new connection"
            )
            assert node.bd_seq == (bd_seq + 1) % 256

            # The new session subscribes to STATE after its CONNACK: an old STATE sent before
            # that is not delivered (it is not retained), so it is sent until one is ignored.
            for _ in range(10):
                host.send(op="rawstate", text='{"online": true, "timestamp": 1000}')
                with contextlib.suppress(AssertionError, TimeoutError):
                    await host.wait(lambda: bool(logged(caplog, topic, "older")), 2, "old STATE")
                    break
            assert logged(caplog, topic, "older"), "the old STATE: not seen in 20 s"
            await asyncio.sleep(2.0)  # births would follow at once: none may come
            assert host.count("NBIRTH") == 1 and not node.born

            host.send(op="state", online=True)
            await host.wait(lambda: host.count("NBIRTH") == 2, 10, "births when back online")
            assert bd_seq_of(host.messages("NBIRTH")[1]) == (bd_seq + 1) % 256
            seen = {m: len(cycles_of(host, m)) for m in MACHINES}
            await host.wait(
                lambda: all(len(cycles_of(host, m)) >= seen[m] + 3 for m in MACHINES),
                20,
                "data again",
            )
            assert node.sessions == 2  # one disconnect: the offline STATE's

        events = host.snapshot()
        assert not [e for e in events if e["event"] == "message" and e["gap"]]
        assert_every_cycle_once_in_order(host, run.records)

    asyncio.run(scenario())


def test_primary_host_crash_its_will_ends_the_session_and_a_new_host_gets_births(
    tmp_path: Path, store: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The host SIGKILLed: the broker publishes its will (offline, with the timestamp of
    its online STATE, as Sparkplug 3.0 has it), which the node takes: NDEATH, a new
    connection that waits; a host started afterwards gets births with bdSeq + 1."""
    monkeypatch.setenv("SPB_TEST_PASSWORD", PASSWORD)

    async def scenario() -> None:
        async with Run(tmp_path, store, {}) as run:
            node = run.gateway.sparkplug
            assert node is not None
            await run.host.wait(lambda: run.host.count("DDATA") >= 3, 60, "data")
            bd_seq = bd_seq_of(run.host.messages("NBIRTH")[0])
            run.host.close()  # SIGKILL
            deadline = time.monotonic() + 30  # the broker sees the dead socket at once
            while not (node.sessions == 2 and node.link is not None and not node.born):
                assert time.monotonic() < deadline, "no new connection after the host's will"
                await asyncio.sleep(0.05)
            run.host = TahuHost(run.broker, GROUP, HOST)
            await run.host.wait(lambda: run.host.count("NBIRTH") == 1, 20, "births")
            assert bd_seq_of(run.host.messages("NBIRTH")[0]) == (bd_seq + 1) % 256
            await run.host.wait(lambda: run.host.count("DDATA") >= 3, 20, "data again")

    asyncio.run(scenario())


def test_bd_seq_counts_every_connect_sent_those_the_broker_refused_too(
    tmp_path: Path, store: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A wrong password: every CONNECT carries a will with a new bdSeq (Sparkplug 3.0),
    so the saved bdSeq counts the refusals (from 0); no births."""
    monkeypatch.setenv("SPB_TEST_PASSWORD", "not-the-password")

    async def scenario() -> Run:
        async with Run(tmp_path, store, {}) as run:
            await run.host.wait(lambda: len(logged(caplog, "Sparkplug:", " refused: ")) >= 3,
                                30, "three refused CONNECTs")  # fmt: skip
            await run.stop_gateway()
        return run

    run = asyncio.run(scenario())
    refused = logged(caplog, "Sparkplug:", " refused: ")
    saved = json.loads((tmp_path / "state" / "sparkplug-bdseq.json").read_text())["bdSeq"]
    assert saved == len(refused) - 1, (saved, refused)
    assert run.host.count("NBIRTH") == 0
