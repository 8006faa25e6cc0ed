"""A multi-axis machine on the SCADA server: an ``Axes`` folder with one folder per axis.

A real ScadaServer on loopback, read by asyncua's client over Basic256Sha256
SignAndEncrypt as a SCADA viewer: the folders exist from the start in configured order
with each axis's macro, and after a cycle is published every axis's nodes hold that
axis's values while the machine's own nodes keep the first axis's. A single-axis
machine on the same server has no ``Axes`` folder.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

from asyncua import Client, ua

from gateway.scada.server import NAMESPACE, ScadaServer
from tests.records import axes_record, written_record
from tests.test_scada import VIEWER, settings
from tests.test_scada_guards import client_certificate
from tests.ua_session import sign_and_encrypt

MULTI, SINGLE, LATE = "vmc-3", "vmc-1", "hmc-2"
MACROS = {"Z": 500, "X": 502, "Y": 504}
APPLIED = {"Z": 12.5, "X": -3.25, "Y": 0.75}


async def viewer_client(server: ScadaServer, folder: Path) -> Client:
    cert, key = await client_certificate(folder)
    client = Client(server.endpoint, timeout=10)
    await sign_and_encrypt(client, cert, key)
    client.set_user(VIEWER.username)
    client.set_password(VIEWER.password)
    await client.connect()
    return client


async def read(client: Client, ns: int, node: str) -> ua.DataValue:
    return await client.get_node(ua.NodeId(node, ns)).read_data_value(raise_on_bad_status=False)


async def child_names(client: Client, ns: int, node: str) -> list[str]:
    children = await client.get_node(ua.NodeId(node, ns)).get_children()
    return [(await c.read_browse_name()).Name for c in children]


def test_axes_folders_carry_each_axis_and_the_machine_nodes_the_first(tmp_path: Path) -> None:
    found: dict[str, object] = {}

    async def main() -> None:
        server = ScadaServer(
            settings(tmp_path / "pki"),
            {MULTI: ["T1"], SINGLE: ["T1"], LATE: ["T1"]},
            lambda machine, enabled: None,
            axes={MULTI: MACROS, SINGLE: {}},
        )
        async with server:
            client = await viewer_client(server, tmp_path / "client")
            try:
                ns = await client.get_namespace_index(NAMESPACE)
                found["before"] = await child_names(client, ns, f"{MULTI}.Axes")
                found["macro before"] = [
                    (await read(client, ns, f"{MULTI}.Axes.{a}.Macro")).Value.Value for a in MACROS
                ]
                found["predicted before"] = (
                    await read(client, ns, f"{MULTI}.Axes.X.PredictedUm")
                ).StatusCode.name
                found["single"] = await child_names(client, ns, SINGLE)
                record = axes_record(MULTI, 60.0, {"T1": 30.0}, APPLIED, stamp_s=1.78e9)
                record.axes["Y"].write_status = "held: link lost"
                record.axes["Y"].outside_inputs = ["T1"]
                record.axes["Y"].training_span = "outside"
                await server.publish(record, {})
                await server.publish(written_record(SINGLE, 60.0, {"T1": 30.0}, 4.0), {})
                # a machine whose axes were not configured gets its folders from a record
                await server.publish(axes_record(LATE, 60.0, {"T1": 30.0}, {"A": 1.5}), {})
                found["after"] = {
                    axis: {
                        name: await read(client, ns, f"{MULTI}.Axes.{axis}.{name}")
                        for name in (
                            "ModelId",
                            "PredictedUm",
                            "IntervalUm",
                            "TrainingSpan",
                            "OutsideInputs",
                            "CompensationUm",
                            "LastWriteStatus",
                            "Macro",
                        )
                    }
                    for axis in MACROS
                }
                found["machine"] = {
                    name: (await read(client, ns, f"{MULTI}.{name}")).Value.Value
                    for name in ("ModelId", "PredictedUm", "CompensationUm", "LastWriteStatus")
                }
                found["single after"] = await child_names(client, ns, SINGLE)
                found["late"] = (
                    await read(client, ns, f"{LATE}.Axes.A.CompensationUm")
                ).Value.Value
            finally:
                await client.disconnect()

    asyncio.run(main())
    assert found["before"] == ["Z", "X", "Y"]  # configured order, before any cycle
    assert found["macro before"] == [500, 502, 504]
    assert found["predicted before"] == "BadWaitingForInitialData"
    assert "Axes" not in found["single"] and "Axes" not in found["single after"]
    after = found["after"]
    assert isinstance(after, dict)
    for index, axis in enumerate(MACROS):
        values = after[axis]
        assert all(v.StatusCode.is_good() for v in values.values()), axis
        assert values["ModelId"].Value.Value == f"lag-ridge-{axis}"
        assert values["PredictedUm"].Value.Value == APPLIED[axis]
        assert values["CompensationUm"].Value.Value == APPLIED[axis]
        assert values["IntervalUm"].Value.Value == 1.0 + 0.5 * index
        assert values["Macro"].Value.Value == MACROS[axis]
        assert values["Macro"].Value.VariantType == ua.VariantType.UInt32
        assert values["PredictedUm"].Value.VariantType == ua.VariantType.Double
    assert after["Y"]["LastWriteStatus"].Value.Value == "held: link lost"
    assert after["Y"]["TrainingSpan"].Value.Value == "outside"
    assert after["Y"]["OutsideInputs"].Value.Value == "T1"
    assert after["Z"]["LastWriteStatus"].Value.Value == "ok"
    assert found["machine"] == {
        "ModelId": "lag-ridge-Z",
        "PredictedUm": 12.5,
        "CompensationUm": 12.5,
        "LastWriteStatus": "ok",
    }
    assert found["late"] == 1.5
    assert not math.isnan(after["X"]["CompensationUm"].Value.Value)
