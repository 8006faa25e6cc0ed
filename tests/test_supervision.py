"""One machine failing leaves the others cycling; failures are counted and published.

Three simulated machines, each serving its transmitters (Modbus TCP) and its CNC
(Modbus TCP) on loopback, compensated by one gateway on an accelerated clock
(×20: a 2 s cycle every 0.1 s of wall time). One machine's log sink fails as a
full disk would, then its loop itself raises; the other two are counted cycle by
cycle meanwhile. The health counters are read back from the heartbeat files and
from the SCADA server with a real OPC UA client (asyncua, Basic256Sha256
SignAndEncrypt, user name and password).
"""

from __future__ import annotations

import asyncio
import errno
import itertools
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

from drivers.backoff import Backoff
from drivers.clock import AcceleratedClock
from gateway.config import GatewayConfig
from gateway.live.record import CycleRecord
from gateway.outputs.heartbeat import check
from gateway.process.supervision import Supervised
from gateway.scada.server import TRUSTED_DIR
from gateway.wiring import Gateway
from simulator.serve import SimulatedPlant
from tests import gateway_rig as rig
from tests.ports import free_tcp_port

SPEEDUP = 20.0
CYCLE_S = 2.0  # machine seconds: 0.1 s of wall time


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("supervision"))


async def wait_until(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout_s:g} s: {what}")
        await asyncio.sleep(0.02)


def full_disk_on(machine: str) -> Callable[[CycleRecord], None]:
    """A log sink that fails for one machine the way a full disk makes a write fail."""

    def write_points(record: CycleRecord) -> None:
        if record.machine == machine:
            raise OSError(errno.ENOSPC, "No space left on device")

    return write_points


def config_for(tmp_path: Path, plants: list[SimulatedPlant], store: Path, **extra: Any) -> Any:
    return GatewayConfig.model_validate(
        {
            "state_dir": str(tmp_path / "state"),
            "logging": {"local_store": str(tmp_path / "data" / "points.sqlite")},
            "machines": [
                rig.machine_entry(f"m{i}", p, store, cycle_s=CYCLE_S) for i, p in enumerate(plants)
            ],
            **extra,
        }
    )


def heartbeat(tmp_path: Path, machine: str) -> dict[str, Any]:
    return json.loads((tmp_path / "state" / f"{machine}-heartbeat.json").read_text())


def test_a_failing_sink_and_a_failing_loop_leave_the_other_machines_cycling(
    tmp_path: Path, store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    faults = {"left": 0}

    async def scenario() -> dict[str, Any]:
        clock = AcceleratedClock(SPEEDUP)
        plants = [rig.plant(clock, seed=i, cnc=("modbus",)) for i in range(3)]
        for served in plants:
            await served.start()
        gateway = Gateway(
            config_for(tmp_path, plants, store), clock=clock, sinks=[full_disk_on("m0")]
        )
        m0, m1, m2 = gateway.loops
        stop = asyncio.Event()
        running = asyncio.create_task(gateway.run(stop))
        figures: dict[str, Any] = {}
        try:
            # 1. m0's log sink fails every cycle: counted, and every machine cycles on.
            await wait_until(lambda: min(loop.cycles for loop in gateway.loops) >= 10, 60, "cycles")
            (name,) = m0.sink_failures
            assert name.endswith("full_disk_on.<locals>.write_points")
            figures["sink_failures"] = m0.sink_failures[name]
            figures["m0_cycles_with_failing_sink"] = m0.cycles
            assert not m1.sink_failures and not m2.sink_failures
            # The others' pace now, on this machine (a loaded one runs slower than the clock).
            paced_from, paced_cycles = time.monotonic(), m1.cycles
            await wait_until(lambda: m1.cycles >= paced_cycles + 10, 60, "ten more cycles")
            figures["wall_s_per_cycle"] = (time.monotonic() - paced_from) / (
                m1.cycles - paced_cycles
            )

            # 2. m0's loop raises (three cycles in a row): it is restarted with back-off.
            real_cycle = m0.run_cycle

            async def failing_cycle() -> CycleRecord:
                if faults["left"] > 0:
                    faults["left"] -= 1
                    raise RuntimeError("injected fault in the cycle")
                return await real_cycle()

            m0.run_cycle = failing_cycle  # type: ignore[method-assign]
            before = {loop.config.id: loop.cycles for loop in gateway.loops}
            started = time.monotonic()
            faults["left"] = 3
            supervisor = gateway.supervisors["m0"]
            await wait_until(lambda: supervisor.restarts == 3, 30, "three restarts of m0")
            await wait_until(lambda: m0.cycles > before["m0"], 30, "m0 cycling again")
            figures["m0_down_s"] = time.monotonic() - started
            figures["cycles_while_m0_down"] = {
                loop.config.id: loop.cycles - before[loop.config.id] for loop in gateway.loops
            }
            await wait_until(lambda: m0.cycles > before["m0"] + 3, 30, "m0 cycles on")
            figures["health"] = gateway.health("m0")
            await asyncio.sleep(0.3)  # a few more cycles, so every heartbeat is fresh
        finally:
            stop.set()
            await asyncio.wait_for(running, 10)
            for served in plants:
                await served.stop()
        figures["heartbeats"] = {m: heartbeat(tmp_path, m) for m in ("m0", "m1", "m2")}
        return figures

    figures = asyncio.run(scenario())
    print(f"supervision: {figures['cycles_while_m0_down']} cycles in {figures['m0_down_s']:.2f} s")
    assert figures["sink_failures"] >= figures["m0_cycles_with_failing_sink"] - 1
    # While m0 was down (≈ 0.5 + 1 + 2 s of restart back-off) the others kept the pace
    # they had just before.
    down = figures["cycles_while_m0_down"]
    assert figures["m0_down_s"] >= 0.4 + 0.8 + 1.6
    expected = figures["m0_down_s"] / max(figures["wall_s_per_cycle"], CYCLE_S / SPEEDUP)
    assert down["m1"] >= 0.5 * expected and down["m2"] >= 0.5 * expected, (down, expected)
    health = figures["health"]
    assert health["loop_restarts"] == 3
    assert health["last_loop_error"] == "RuntimeError: injected fault in the cycle"
    assert health["sink_failures"] >= figures["sink_failures"]
    # The heartbeat carries the counters; the health check stays healthy and names them.
    beat = figures["heartbeats"]["m0"]["health"]
    assert beat["loop_restarts"] == 3 and beat["sink_failures"] > 0
    assert list(beat["sink_failures_by_sink"].values()) == [beat["sink_failures"]]
    assert figures["heartbeats"]["m1"]["health"]["loop_restarts"] == 0
    assert figures["heartbeats"]["m1"]["health"]["sink_failures"] == 0
    healthy, message = check(tmp_path / "state", max_age_s=60)
    assert healthy, message
    assert "m0" in message and "loop_restarts 3" in message and "sink_failures" in message
    # Logged with the traceback once each, however often it failed.
    tracebacks = [r for r in caplog.records if r.exc_info]
    assert len([r for r in tracebacks if "sink" in r.getMessage()]) == 1
    assert len([r for r in tracebacks if "machine m0 loop failed" in r.getMessage()]) == 1
    assert sum("failed again" in r.getMessage() for r in caplog.records) == 2


async def read_health_over_opcua(
    endpoint: str, client_dir: Path, pki: Path, user: str, password: str, machine: str
) -> dict[str, Any]:
    """Read every Health node of ``machine`` with asyncua's client, as a SCADA would."""
    client = Client(endpoint, timeout=10)
    cert, key = client_dir / "client_cert.der", client_dir / "client_key.pem"
    await setup_self_signed_certificate(
        key, cert, client.application_uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {}
    )
    (pki / TRUSTED_DIR).mkdir(parents=True, exist_ok=True)
    (pki / TRUSTED_DIR / "health-client.der").write_bytes(cert.read_bytes())
    await client.set_security(
        SecurityPolicyBasic256Sha256,
        str(cert),
        str(key),
        mode=ua.MessageSecurityMode.SignAndEncrypt,
    )
    client.set_user(user)
    client.set_password(password)
    async with client:
        ns = await client.get_namespace_index("urn:spindle-gateway:scada")
        health = client.get_node(ua.NodeId(f"{machine}.Health", ns))
        values = {}
        for node in await health.get_children():
            name = (await node.read_browse_name()).Name
            values[name] = await node.read_value()
        return values


def test_health_is_published_over_scada_and_in_the_heartbeat(tmp_path: Path, store: Path) -> None:
    password_file = tmp_path / "viewer.secret"
    password_file.write_text("view-secret-7\n")
    pki = tmp_path / "pki"

    async def scenario() -> tuple[dict[str, Any], dict[str, Any]]:
        clock = AcceleratedClock(SPEEDUP)
        plants = [rig.plant(clock, seed=i, cnc=("modbus",)) for i in range(2)]
        for served in plants:
            await served.start()
        scada = {
            "port": free_tcp_port(),
            "pki_dir": str(pki),
            "users": [{"username": "victor", "password_file": str(password_file)}],
        }
        config = config_for(tmp_path, plants, store, scada=scada)
        gateway = Gateway(config, clock=clock, sinks=[full_disk_on("m1")])
        stop = asyncio.Event()
        running = asyncio.create_task(gateway.run(stop))
        try:
            m1 = gateway.loops[1]
            await wait_until(lambda: m1.cycles >= 20, 60, "20 cycles")
            await plants[1].take_down("cnc_modbus")  # link errors on m1
            await wait_until(lambda: m1.link_errors >= 5, 30, "link errors")
            await plants[1].bring_up("cnc_modbus")
            assert gateway.scada is not None
            values = await read_health_over_opcua(
                gateway.scada.endpoint, tmp_path, pki, "victor", "view-secret-7", "m1"
            )
            expected = gateway.health("m1")
        finally:
            stop.set()
            await asyncio.wait_for(running, 10)
            for served in plants:
                await served.stop()
        return values, expected

    values, expected = asyncio.run(scenario())
    names = {
        "FailedWrites",
        "Cycles",
        "LinkErrors",
        "ExternalChanges",
        "LinkErrorsTotal",
        "SinkFailures",
        "LoopRestarts",
        "ForwarderBacklog",
        "DroppedPoints",
        "RejectedPoints",
        "ForwarderRestarts",
        "ModelSwaps",
        "ModelSwapsRefused",
    }
    assert set(values) == names
    assert values["ModelSwaps"] == 0 and values["ModelSwapsRefused"] == 0  # nothing promoted
    # Published after each cycle: the client read what the gateway counted a cycle or two before.
    assert 20 <= values["Cycles"] <= expected["cycles"]
    assert 5 <= values["LinkErrorsTotal"] <= expected["link_errors_total"]
    assert values["SinkFailures"] >= 20 and values["SinkFailures"] <= expected["sink_failures"]
    assert values["LoopRestarts"] == 0 and values["ForwarderBacklog"] == 0
    beat = heartbeat(tmp_path, "m1")["health"]
    assert beat["sink_failures"] >= values["SinkFailures"]
    assert beat["link_errors_total"] >= values["LinkErrorsTotal"]
    assert heartbeat(tmp_path, "m0")["health"]["sink_failures"] == 0


# -- the supervisor on its own (no I/O) -------------------------------------------------


def test_supervisor_restarts_with_growing_back_off_reset_by_progress() -> None:
    progress = {"cycles": 0}
    starts: list[float] = []

    async def task(stop: asyncio.Event) -> None:
        starts.append(time.monotonic())
        if len(starts) == 4:
            progress["cycles"] += 1  # this run did some work before failing
        if len(starts) < 6:
            raise ValueError("boom")
        stop.set()

    supervised = Supervised("task", task, progress=lambda: progress["cycles"])
    supervised.backoff = Backoff(initial_s=0.05, factor=2.0, max_s=0.2, jitter=0.0)
    asyncio.run(asyncio.wait_for(supervised.supervise(asyncio.Event()), 10))
    gaps = [round(b - a, 2) for a, b in itertools.pairwise(starts)]
    assert supervised.restarts == 5 and supervised.last_error == "ValueError: boom"
    # 0.05, 0.1, 0.2, then progress was made: back to 0.05, then 0.1
    assert gaps == pytest.approx([0.05, 0.1, 0.2, 0.05, 0.1], abs=0.04)


def test_supervisor_back_off_is_cut_short_by_stop_and_cancel_is_not_a_failure() -> None:
    async def failing(stop: asyncio.Event) -> None:
        raise OSError("disk full")

    async def scenario() -> tuple[float, Supervised, Supervised]:
        stop = asyncio.Event()
        supervised = Supervised("failing", failing)
        supervised.backoff = Backoff(initial_s=30.0, max_s=30.0, jitter=0.0)
        running = asyncio.create_task(supervised.supervise(stop))
        await asyncio.sleep(0.05)
        started = time.monotonic()
        stop.set()
        await asyncio.wait_for(running, 5)
        waited = time.monotonic() - started

        forever = Supervised("forever", lambda stop: asyncio.Event().wait())
        task = asyncio.create_task(forever.supervise(asyncio.Event()))
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return waited, supervised, forever

    waited, supervised, forever = asyncio.run(scenario())
    assert waited < 0.5  # not the 30 s back-off
    assert supervised.restarts == 0 and supervised.last_error == "OSError: disk full"
    assert forever.restarts == 0 and forever.last_error is None
