"""The gateway's secured OPC UA server for SCADA, checked with an independent client.

A real ScadaServer on loopback with its own PKI in a temporary folder; the client
is node-opcua (``tests/node/scada_client.mjs``) in a Node subprocess, connecting
with Basic256Sha256 SignAndEncrypt and a user name and password, as a SCADA
would. Where node-opcua refuses on its own before asking the server (a mode or
an identity the endpoint does not offer), the server side is checked as well by
driving asyncua's client at the protocol level, so the refusal is proven to come
from the server and not from a polite client.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import shutil
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography.x509.oid import ExtendedKeyUsageOID

from gateway.live.record import CycleRecord
from gateway.scada.server import (
    CRL_DIR,
    NAMESPACE,
    REJECTED_DIR,
    SERVER_CERT,
    SERVER_KEY,
    TRUSTED_DIR,
    ScadaServer,
    ScadaSettings,
    ScadaUser,
)
from tests.node_process import NODE_DIR, run_node
from tests.ports import free_tcp_port
from tests.ua_session import (
    activate,
    create_session,
    open_channel,
    password_token,
    sign_and_encrypt,
)

NODE_CLIENT = NODE_DIR / "scada_client.mjs"
MACHINE = "vmc-1"

OPERATOR = ScadaUser("alice", "op-secret-1", "operator")
VIEWER = ScadaUser("victor", "view-secret-2", "viewer")


@pytest.fixture(scope="module")
def node_pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One node-opcua PKI for the module: its client certificate is made only once."""
    if shutil.which("node") is None or not (NODE_DIR / "node_modules").is_dir():
        raise RuntimeError("node and tests/node/node_modules are needed (npm ci in tests/node)")
    return tmp_path_factory.mktemp("node-pki")


def settings(pki_dir: Path, **changes: object) -> ScadaSettings:
    values: dict[str, object] = {
        "port": free_tcp_port(),
        "pki_dir": pki_dir,
        "users": (OPERATOR, VIEWER),
        "trust_all_clients": True,
    }
    values.update(changes)
    return ScadaSettings(**values)  # type: ignore[arg-type]


#: The wall time of the known cycle's start (Unix s): its values' source timestamp.
STAMP_S = 1_780_000_000.25


def known_record() -> CycleRecord:
    return CycleRecord(
        machine=MACHINE,
        time_s=3600.0,
        temperatures_C={"spindle_front": 41.25, "spindle_rear": None, "motor": 35.5},
        quality={"spindle_front": "good", "spindle_rear": "bad", "motor": "bad"},
        quality_reasons={"spindle_rear": "stale for 12 s", "motor": "recovering (1/3 good)"},
        speed_rpm=8000.0,
        regime="high",
        model_id="mlr-high-v3",
        predicted_um=12.5,
        target_um=12.0,
        applied_um=11.75,
        written_cnc=0.01175,
        write_status="ok",
        link_errors=["bus-a: timeout", "bus-b: timeout"],
        stamp_s=STAMP_S,
    )


HEALTH = {"failed_writes": 2, "cycles": 360, "compensation_enabled": True}


async def node_client(
    server: ScadaServer,
    operations: list[dict[str, object]],
    pki: Path,
    *,
    user: ScadaUser | None = None,
    password: str | None = None,
    mode: str = "SignAndEncrypt",
) -> tuple[int, dict]:
    """Run the node-opcua client while this event loop keeps serving."""
    args = [str(NODE_CLIENT), server.endpoint, json.dumps(operations), "--pki", str(pki)]
    args += ["--mode", mode]
    if user is None:
        args.append("--anonymous")
    else:
        args += [
            "--user",
            user.username,
            "--password",
            user.password if password is None else password,
        ]
    returncode, out, err = await run_node(*args)
    lines = out.decode().strip().splitlines()
    assert lines, f"no output (exit {returncode}): {err.decode()[-2000:]}"
    return returncode, json.loads(lines[-1])


def statuses(reply: dict) -> list[str]:
    return [r["status"] for r in reply["results"]]


def run_with_server(
    scada_settings: ScadaSettings,
    scenario: Callable[[ScadaServer, list[tuple[str, bool]]], Awaitable[None]],
) -> list[tuple[str, bool]]:
    """Start a server with the known record published, run the scenario, return on_enable calls."""
    calls: list[tuple[str, bool]] = []

    async def main() -> None:
        server = ScadaServer(
            scada_settings,
            {MACHINE: ["spindle_front", "spindle_rear", "motor"], "hmc-2": [], "hmc-3": []},
            lambda machine, enabled: calls.append((machine, enabled)),
        )
        async with server:
            await server.publish(known_record(), HEALTH)
            await scenario(server, calls)

    asyncio.run(main())
    return calls


# -- protocol-level probes with asyncua's client (server-side enforcement) -------------


async def raw_activate(
    endpoint: str,
    token: ua.UserNameIdentityToken | ua.AnonymousIdentityToken,
    cert_dir: Path | None,
) -> str:
    """Open a channel (secure if cert_dir), create a session, activate it with ``token``.

    Skips the client-side checks a well-behaved client makes against the endpoint
    list, like a hostile or misconfigured client would. Returns the status name.
    """
    client = Client(endpoint, timeout=10)
    if cert_dir is not None:
        cert, key = cert_dir / "probe_cert.der", cert_dir / "probe_key.pem"
        await setup_self_signed_certificate(
            key,
            cert,
            client.application_uri,
            "localhost",
            [ExtendedKeyUsageOID.CLIENT_AUTH],
            {},
        )
        await sign_and_encrypt(client, cert, key)
    try:
        await open_channel(client)
        created = await create_session(client, endpoint, "probe")
        return await activate(client, created, token, signed=cert_dir is not None)
    finally:
        client.disconnect_socket()


# -- tests ---------------------------------------------------------------------------


def test_reads_live_values_over_sign_and_encrypt(tmp_path: Path, node_pki: Path) -> None:
    ids = [
        "Temperatures.spindle_front",
        "Temperatures.spindle_rear",
        "Temperatures.motor",
        "SpeedRpm",
        "Regime",
        "ModelId",
        "PredictedUm",
        "CompensationUm",
        "LastWriteStatus",
        "Health.FailedWrites",
        "Health.Cycles",
        "Health.LinkErrors",
        "CompensationEnabled",
    ]
    replies: list[dict] = []

    async def scenario(server: ScadaServer, calls: list) -> None:
        # A sensor first seen in a record gets its node then (here through the sink path).
        later = dataclasses.replace(
            known_record(),
            machine="hmc-3",
            temperatures_C={"column": 22.5},
            quality={"column": "good"},
        )
        await server.publish_soon(later, {"cycles": 1})
        ops = [{"read": f"{MACHINE}.{i}"} for i in ids] + [
            {"read": "hmc-3.Temperatures.column"},
            {"read": f"{MACHINE}.SpeedRpm.EngineeringUnits"},
            {"read": f"{MACHINE}.Temperatures.motor.EngineeringUnits"},
            {"read": "hmc-2.SpeedRpm"},
        ]
        code, reply = await node_client(server, ops, node_pki, user=VIEWER)
        assert code == 0, reply
        replies.append(reply)

    run_with_server(settings(tmp_path / "pki"), scenario)
    *values, column, rpm_unit, celsius_unit, waiting = replies[0]["results"]
    results = {r["nodeId"].split(".", 1)[1]: r for r in values}
    expected = {
        "Temperatures.spindle_front": ("Good", "Double", 41.25),
        "Temperatures.motor": ("Uncertain", "Double", 35.5),
        "SpeedRpm": ("Good", "Double", 8000),
        "Regime": ("Good", "String", "high"),
        "ModelId": ("Good", "String", "mlr-high-v3"),
        "PredictedUm": ("Good", "Double", 12.5),
        "CompensationUm": ("Good", "Double", 11.75),
        "LastWriteStatus": ("Good", "String", "ok"),
        "Health.FailedWrites": ("Good", "UInt32", 2),
        "Health.Cycles": ("Good", "UInt32", 360),
        "Health.LinkErrors": ("Good", "UInt32", 2),
        "CompensationEnabled": ("Good", "Boolean", True),
    }
    for name, (status, data_type, value) in expected.items():
        got = results[name]
        assert (got["status"], got["dataType"], got["value"]) == (status, data_type, value), name
    assert results["Temperatures.spindle_rear"]["status"] == "BadSensorFailure"
    # Every value carries the time its cycle started, as its logged points and Sparkplug do.
    assert {r["sourceTimestampMs"] for n, r in results.items() if n != "CompensationEnabled"} == {
        STAMP_S * 1000
    }
    # A machine with nothing published yet says so rather than showing a fake zero.
    assert waiting["status"] == "BadWaitingForInitialData"
    assert (column["status"], column["value"]) == ("Good", 22.5)
    # Units as EngineeringUnits properties (UNECE codes: "RPM", "CEL").
    assert rpm_unit["value"]["displayName"]["text"] == "r/min"
    assert rpm_unit["value"]["unitId"] == int.from_bytes(b"RPM", "big")
    assert celsius_unit["value"]["unitId"] == int.from_bytes(b"CEL", "big")


def test_wrong_password_and_default_anonymous_are_refused(tmp_path: Path, node_pki: Path) -> None:
    async def scenario(server: ScadaServer, calls: list) -> None:
        read = [{"read": f"{MACHINE}.SpeedRpm"}]
        code, reply = await node_client(server, read, node_pki, user=OPERATOR, password="guess")
        assert code == 1 and reply["status"] == "BadUserAccessDenied", reply
        code, reply = await node_client(server, read, node_pki, user=VIEWER, password="")
        assert code == 1, reply

        # node-opcua does not even try anonymous: the endpoint offers no such token...
        code, reply = await node_client(server, read, node_pki, user=None)
        assert code == 1 and "ANONYMOUS" in reply["error"], reply
        # ...and the server refuses it when a client sends one anyway.
        token = ua.AnonymousIdentityToken(PolicyId="anonymous")
        status = await raw_activate(server.endpoint, token, probe)
        assert status == "BadIdentityTokenRejected"
        # (the same probe with a valid user is let in: the refusal is about the token)
        assert await raw_activate(server.endpoint, password_token(VIEWER), probe) == "Good"

    probe = tmp_path / "probe"
    probe.mkdir()
    run_with_server(settings(tmp_path / "pki"), scenario)


def test_allowed_anonymous_reads_but_cannot_write(tmp_path: Path, node_pki: Path) -> None:
    async def scenario(server: ScadaServer, calls: list) -> None:
        ops = [
            {"read": f"{MACHINE}.PredictedUm"},
            {"write": f"{MACHINE}.CompensationEnabled", "value": False},
            {"read": f"{MACHINE}.CompensationEnabled"},
        ]
        code, reply = await node_client(server, ops, node_pki, user=None)
        assert code == 0, reply
        assert reply["results"][0]["value"] == 12.5
        assert statuses(reply) == ["Good", "BadUserAccessDenied", "Good"]
        assert reply["results"][2]["value"] is True

    calls = run_with_server(settings(tmp_path / "pki", allow_anonymous=True), scenario)
    assert calls == []


def test_only_operators_switch_compensation(tmp_path: Path, node_pki: Path) -> None:
    seen_during: list[list] = []

    async def scenario(server: ScadaServer, calls: list) -> None:
        switch = f"{MACHINE}.CompensationEnabled"
        ops = [{"write": switch, "value": False}, {"read": switch}]
        code, reply = await node_client(server, ops, node_pki, user=VIEWER)
        assert code == 0, reply
        assert statuses(reply) == ["BadUserAccessDenied", "Good"]
        assert reply["results"][1]["value"] is True
        seen_during.append(list(calls))

        code, reply = await node_client(server, ops, node_pki, user=OPERATOR)
        assert code == 0, reply
        assert statuses(reply) == ["Good", "Good"]
        assert reply["results"][1]["value"] is False

        # Only the switch is writable, and only as a Boolean.
        ops = [
            {"write": f"{MACHINE}.PredictedUm", "value": 1.0},
            {"write": switch, "value": 1.0},
        ]
        code, reply = await node_client(server, ops, node_pki, user=OPERATOR)
        assert code == 0, reply
        assert statuses(reply) == ["BadUserAccessDenied", "BadTypeMismatch"]

    calls = run_with_server(settings(tmp_path / "pki"), scenario)
    assert seen_during == [[]]
    assert calls == [(MACHINE, False)]


def test_no_unsecured_access(tmp_path: Path, node_pki: Path) -> None:
    async def scenario(server: ScadaServer, calls: list) -> None:
        read = [{"read": f"{MACHINE}.SpeedRpm"}]
        code, reply = await node_client(server, read, node_pki, user=OPERATOR, mode="None")
        assert code == 1 and "End point must exist" in reply["error"], reply
        # A client that ignores the endpoint list and sends the (right) password over an
        # unsecured channel still gets no session.
        status = await raw_activate(server.endpoint, password_token(OPERATOR), None)
        assert status == "BadUserAccessDenied"

    run_with_server(settings(tmp_path / "pki"), scenario)


async def refused_then_trusted(
    server: ScadaServer, pki: Path, read: list[dict[str, str]], node_pki: Path
) -> Path:
    """The node-opcua client refused as untrusted, its certificate kept in rejected/, then
    moved to trusted/ as an engineer does after checking the thumbprint (its new path)."""
    code, reply = await node_client(server, read, node_pki, user=VIEWER)
    assert code == 1 and reply["status"] == "BadCertificateUntrusted", reply
    (rejected,) = (pki / REJECTED_DIR).glob("*.der")
    return rejected.rename(pki / TRUSTED_DIR / rejected.name)


def test_untrusted_client_refused_until_trusted_and_certificate_kept(
    tmp_path: Path, node_pki: Path
) -> None:
    pki = tmp_path / "pki"
    scada_settings = settings(pki, trust_all_clients=False)
    read = [{"read": f"{MACHINE}.ModelId"}]

    async def first_run(server: ScadaServer, calls: list) -> None:
        await refused_then_trusted(server, pki, read, node_pki)
        code, reply = await node_client(server, read, node_pki, user=VIEWER)
        assert code == 0 and reply["results"][0]["value"] == "mlr-high-v3", reply

    run_with_server(scada_settings, first_run)
    cert, key = (pki / SERVER_CERT).read_bytes(), (pki / SERVER_KEY).read_bytes()
    assert (pki / SERVER_KEY).stat().st_mode & 0o077 == 0

    async def second_run(server: ScadaServer, calls: list) -> None:
        assert server.namespace_index >= 1
        code, reply = await node_client(server, read, node_pki, user=VIEWER)
        assert code == 0, reply

    run_with_server(scada_settings, second_run)
    assert (pki / SERVER_CERT).read_bytes() == cert
    assert (pki / SERVER_KEY).read_bytes() == key


def test_settings_and_constructor_are_checked(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        ScadaUser("x", "pw", "admin")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        ScadaSettings(port=4840, pki_dir=tmp_path, users=(OPERATOR, OPERATOR))
    with pytest.raises(ValueError):
        ScadaServer(settings(tmp_path), ["m", "m"], lambda m, e: None)
    assert "op-secret" not in repr(OPERATOR)
    # Constructing does no I/O: no PKI folder until start().
    server = ScadaServer(settings(tmp_path / "pki"), [MACHINE], lambda m, e: None)
    assert not (tmp_path / "pki").exists()
    assert server.endpoint.startswith("opc.tcp://127.0.0.1:")
    assert NAMESPACE == "urn:spindle-gateway:scada"


def test_a_damaged_file_in_trusted_or_crl_does_not_lock_out_the_trusted_clients(
    tmp_path: Path, node_pki: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An engineer copies a wrong file into trusted/ (a private key, a cut-short copy) or
    crl/: the other trusted certificates still count, and the file is named once."""
    pki = tmp_path / "pki"
    scada_settings = settings(pki, trust_all_clients=False)
    read = [{"read": f"{MACHINE}.ModelId"}]

    async def check(server: ScadaServer, calls: list) -> None:
        trusted = await refused_then_trusted(server, pki, read, node_pki)
        (pki / TRUSTED_DIR / "client_key.pem").write_text("-----BEGIN PRIVATE KEY-----\nAA==\n")
        (pki / TRUSTED_DIR / "copy.der").write_bytes(trusted.name.encode())  # not DER
        (pki / CRL_DIR / "revoked.pem").write_text("not a revocation list\n")
        for _ in range(2):
            code, reply = await node_client(server, read, node_pki, user=VIEWER)
            assert code == 0 and reply["results"][0]["value"] == "mlr-high-v3", reply

    with caplog.at_level(logging.WARNING, logger="gateway.scada.server"):
        run_with_server(scada_settings, check)
    skipped = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(skipped) == 3, skipped  # each file named once, not at every session
    for name in ("client_key.pem", "copy.der", "revoked.pem"):
        assert sum(name in message for message in skipped) == 1, skipped
