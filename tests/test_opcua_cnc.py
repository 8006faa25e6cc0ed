"""The simulated CNC's OPC UA server, checked by two independent client stacks.

Real servers on loopback, real clients (asyncua in-process, node-opcua in a Node
subprocess), a FixedLink with known values behind the server. No mocks: what a
gateway or a SCADA client would see is what is asserted.
"""

from __future__ import annotations

import asyncio
import json
import math
import shutil
import socket
import time
from pathlib import Path

import pytest
from asyncua import Client, ua

from simulator.link import FixedLink, MachineSnapshot, RunMode
from simulator.servers.opcua_cnc import CncOpcUaServer
from tests.node_process import NODE_DIR, run_node

NAMESPACE = "urn:spindle-gateway:simulated-cnc"
NODE_CLIENT = NODE_DIR / "opcua_client.mjs"


def free_port() -> int:
    """A TCP port that was free a moment ago on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def known_snapshot(**changes: object) -> MachineSnapshot:
    values: dict[str, object] = {
        "time_s": 3600.0,
        "channels": {},
        "actual_speed_rpm": 4000.0,
        "commanded_speed_rpm": 4500.0,
        "run_mode": RunMode.AUTO,
        "macros": {500: 0.0125},
        "probe_error_um": 3.25,
    }
    values.update(changes)
    return MachineSnapshot(**values)  # type: ignore[arg-type]


def make_server(link: FixedLink) -> CncOpcUaServer:
    return CncOpcUaServer(link, port=free_port())


def node(client: Client, server: CncOpcUaServer, nodeid: str):
    return client.get_node(ua.NodeId(nodeid, server.namespace_index))


async def read(client: Client, server: CncOpcUaServer, nodeid: str) -> ua.Variant:
    dv = await node(client, server, nodeid).read_data_value()
    assert dv.StatusCode is not None and dv.StatusCode.is_good(), (nodeid, dv.StatusCode)
    assert dv.Value is not None
    return dv.Value


def double(value: float) -> ua.Variant:
    return ua.Variant(value, ua.VariantType.Double)


class Changes:
    """An asyncua subscription handler that keeps the values it is notified of."""

    def __init__(self) -> None:
        self.values: list[object] = []
        self._event = asyncio.Event()

    def datachange_notification(self, node: object, val: object, data: object) -> None:
        self.values.append(val)
        self._event.set()

    async def wait_for(self, value: object, timeout: float = 5.0) -> None:
        async def until_seen() -> None:
            while value not in self.values:
                self._event.clear()
                await self._event.wait()

        await asyncio.wait_for(until_seen(), timeout)


# -- no network -----------------------------------------------------------------------


def test_ids_endpoint_and_argument_checks() -> None:
    link = FixedLink(known_snapshot())
    server = CncOpcUaServer(link, port=4840)
    assert server.endpoint == "opc.tcp://127.0.0.1:4840/cnc"
    assert CncOpcUaServer.macro_node_id(500) == "Macro.500"
    assert CncOpcUaServer.macro_node_id(999) == "Macro.999"
    with pytest.raises(RuntimeError, match="after start"):
        _ = server.namespace_index
    # Only the retained common variables #500–#999 can be served: the link refuses others.
    with pytest.raises(ValueError, match="macro_range"):
        CncOpcUaServer(link, port=4840, macro_range=(100, 599))
    with pytest.raises(ValueError, match="macro_range"):
        CncOpcUaServer(link, port=4840, macro_range=(600, 500))
    with pytest.raises(ValueError, match="port"):
        CncOpcUaServer(link, port=0)


# -- asyncua client ---------------------------------------------------------------------


def test_startup_builds_the_tree_and_all_500_macros_quickly() -> None:
    async def scenario() -> float:
        server = make_server(FixedLink(known_snapshot()))
        started = time.perf_counter()
        await server.start()
        elapsed = time.perf_counter() - started
        try:
            async with Client(server.endpoint, timeout=5) as client:
                ns = await client.get_namespace_index(NAMESPACE)
                assert ns == server.namespace_index
                cnc = await client.nodes.objects.get_child([f"{ns}:CNC"])
                names = [(await c.read_browse_name()).Name for c in await cnc.get_children()]
                assert names == ["Spindle", "Cnc", "Probe", "Macros"]
                macros = await cnc.get_child([f"{ns}:Macros"])
                children = await macros.get_children()
                assert len(children) == 500
                assert {c.nodeid.Identifier for c in children} == {
                    f"Macro.{n}" for n in range(500, 1000)
                }
                first = client.get_node(ua.NodeId("Macro.500", ns))
                assert (await first.read_display_name()).Text == "#500"
                for outside in ("Macro.499", "Macro.1000"):
                    dv = await node(client, server, outside).read_attribute(
                        ua.AttributeIds.Value, raise_on_bad_status=False
                    )
                    assert dv.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown
                speed = await cnc.get_child([f"{ns}:Spindle", f"{ns}:ActualSpeed"])
                unit = await speed.get_child(["0:EngineeringUnits"])
                assert (await unit.read_value()).DisplayName.Text == "r/min"
        finally:
            await server.stop()
        return elapsed

    elapsed = asyncio.run(scenario())
    print(f"start-up with 500 macro nodes: {elapsed:.2f} s")
    # A hang guard, not a benchmark: ≈ 2 s alone, most of it asyncua's init; 13 s was seen
    # with the suite's other worker building the edge image beside it.
    assert elapsed < 30.0


def test_asyncua_reads_every_node_with_its_type_and_value() -> None:
    async def scenario() -> None:
        async with (
            make_server(FixedLink(known_snapshot())) as server,
            Client(server.endpoint, timeout=5) as client,
        ):
            expected = {
                "Spindle.ActualSpeed": (ua.VariantType.Double, 4000.0),
                "Spindle.CommandedSpeed": (ua.VariantType.Double, 4500.0),
                "Cnc.RunMode": (ua.VariantType.Int32, int(RunMode.AUTO)),
                "Cnc.MachineTime": (ua.VariantType.Double, 3600.0),
                "Probe.Error": (ua.VariantType.Double, 3.25),
                "Macro.500": (ua.VariantType.Double, 0.0125),
                "Macro.999": (ua.VariantType.Double, 0.0),  # not in the snapshot: initial 0
            }
            for nodeid, (vtype, value) in expected.items():
                variant = await read(client, server, nodeid)
                assert (variant.VariantType, variant.Value) == (vtype, value), nodeid
            for nodeid in expected:
                datatype = await node(client, server, nodeid).read_data_type()
                want = ua.ObjectIds.Int32 if nodeid == "Cnc.RunMode" else ua.ObjectIds.Double
                assert datatype == ua.NodeId(want), nodeid

    asyncio.run(scenario())


def test_asyncua_macro_write_reaches_the_link_and_survives_publish() -> None:
    async def scenario() -> None:
        link = FixedLink(known_snapshot())
        async with make_server(link) as server, Client(server.endpoint, timeout=5) as client:
            await node(client, server, "Macro.500").write_value(double(0.0375))
            # Forwarded inside the Write service: the link has it when the write returns.
            assert link.writes == [(500, 0.0375)]
            assert (await read(client, server, "Macro.500")).Value == 0.0375
            # The next snapshot reflects the write, so publishing keeps the client's value.
            await server.publish()
            assert (await read(client, server, "Macro.500")).Value == 0.0375
            assert link.writes == [(500, 0.0375)]  # publishing echoes nothing to the link

    asyncio.run(scenario())


def test_refused_writes_leave_node_and_link_untouched() -> None:
    async def scenario() -> None:
        link = FixedLink(known_snapshot())
        async with make_server(link) as server, Client(server.endpoint, timeout=5) as client:
            macro = node(client, server, "Macro.500")
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await macro.write_value(ua.Variant(1, ua.VariantType.Int64))
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await macro.write_value(ua.Variant("0.5", ua.VariantType.String))
            with pytest.raises(ua.uaerrors.BadOutOfRange):
                await macro.write_value(double(math.nan))
            speed = node(client, server, "Spindle.ActualSpeed")
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await speed.write_value(double(1.0))
            assert refused.value.code == ua.StatusCodes.BadUserAccessDenied

            assert link.writes == []
            assert (await read(client, server, "Macro.500")).Value == 0.0125
            assert (await read(client, server, "Spindle.ActualSpeed")).Value == 4000.0

            # No way round read-only: named users (asyncua's built-in "admin") are rejected.
            admin = Client(server.endpoint, timeout=5)
            admin.set_user("admin")
            admin.set_password("admin")
            with pytest.raises(ua.uaerrors.BadIdentityTokenRejected):
                await admin.connect()
            await admin.disconnect()

    asyncio.run(scenario())


def test_publish_shows_a_new_snapshot() -> None:
    async def scenario() -> None:
        link = FixedLink(known_snapshot())
        async with make_server(link) as server, Client(server.endpoint, timeout=5) as client:
            seen = Changes()
            subscription = await client.create_subscription(20, seen)
            await subscription.subscribe_data_change(node(client, server, "Macro.777"))
            await seen.wait_for(0.0)
            link.set_snapshot(
                known_snapshot(
                    time_s=3660.5,
                    actual_speed_rpm=0.0,
                    commanded_speed_rpm=0.0,
                    run_mode=RunMode.STOP,
                    macros={500: -0.002, 777: 42.0},
                    probe_error_um=None,
                )
            )
            assert (await read(client, server, "Spindle.ActualSpeed")).Value == 4000.0
            await server.publish()
            assert (await read(client, server, "Spindle.ActualSpeed")).Value == 0.0
            assert (await read(client, server, "Spindle.CommandedSpeed")).Value == 0.0
            assert (await read(client, server, "Cnc.RunMode")).Value == int(RunMode.STOP)
            assert (await read(client, server, "Cnc.MachineTime")).Value == 3660.5
            assert math.isnan((await read(client, server, "Probe.Error")).Value)
            assert (await read(client, server, "Macro.500")).Value == -0.002
            assert (await read(client, server, "Macro.777")).Value == 42.0
            await seen.wait_for(42.0)  # subscribers are notified of published changes
            assert link.writes == []

    asyncio.run(scenario())


def test_start_fails_cleanly_when_the_port_is_taken() -> None:
    async def scenario() -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
            taken.bind(("127.0.0.1", 0))
            taken.listen()
            server = CncOpcUaServer(FixedLink(known_snapshot()), port=taken.getsockname()[1])
            with pytest.raises(OSError):
                await server.start()
            await server.stop()  # nothing left running; stop() is a no-op
            with pytest.raises(RuntimeError, match="not started"):
                await server.publish()

    asyncio.run(scenario())


# -- node-opcua client (an independent stack) -------------------------------------------


async def run_node_client(endpoint: str, operations: list[dict], pki: Path) -> dict:
    assert shutil.which("node"), "Node.js is needed for the node-opcua tests"
    returncode, out, err = await run_node(
        str(NODE_CLIENT), endpoint, json.dumps(operations), "--pki", str(pki)
    )
    assert returncode == 0, err.decode(errors="replace")
    return json.loads(out)


def test_node_opcua_reads_and_writes_a_macro(tmp_path: Path) -> None:
    async def scenario() -> dict:
        link = FixedLink(known_snapshot())
        async with make_server(link) as server:
            reply = await run_node_client(
                server.endpoint,
                [
                    {"read": "Spindle.ActualSpeed"},
                    {"read": "Cnc.RunMode"},
                    {"read": "Macro.500"},
                    {"write": "Macro.501", "value": 0.0042},
                    {"read": "Macro.501"},
                    {"write": "Spindle.ActualSpeed", "value": 1.0},
                ],
                tmp_path / "pki",
            )
            assert reply["namespaceIndex"] == server.namespace_index
        assert link.writes == [(501, 0.0042)]
        return reply

    reply = asyncio.run(scenario())
    results = reply["results"]
    assert [r["status"] for r in results] == ["Good"] * 5 + ["BadUserAccessDenied"]
    assert (results[0]["dataType"], results[0]["value"]) == ("Double", 4000.0)
    assert (results[1]["dataType"], results[1]["value"]) == ("Int32", int(RunMode.AUTO))
    assert (results[2]["dataType"], results[2]["value"]) == ("Double", 0.0125)
    assert (results[4]["dataType"], results[4]["value"]) == ("Double", 0.0042)
    assert (tmp_path / "pki" / "own").is_dir()  # the client's PKI stayed in the test folder


def test_node_opcua_client_fails_on_no_server(tmp_path: Path) -> None:
    endpoint = f"opc.tcp://127.0.0.1:{free_port()}/cnc"
    returncode, out, err = asyncio.run(
        run_node(str(NODE_CLIENT), endpoint, "[]", "--pki", str(tmp_path / "pki"))
    )
    assert returncode == 1
    assert out == b""
    assert b"cannot connect" in err
