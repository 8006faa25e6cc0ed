"""A burst of trusted SCADA clients connecting at once: every one is admitted.

Fifty asyncua clients open Basic256Sha256 SignAndEncrypt sessions with a password
at the same moment against a real ScadaServer whose trust list holds their
certificates: once with fifty distinct certificates, once with one certificate
shared by all (a SCADA with many stations cloned from one image). The server checks
each certificate at CreateSession while other sessions are being activated; no
trusted client may be refused for a verdict that another session's check was
still working on.
"""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography.x509.oid import ExtendedKeyUsageOID

from gateway.scada.server import TRUSTED_DIR, ScadaServer, ScadaSettings, ScadaUser
from tests.ports import free_tcp_port
from tests.ua_session import (
    activate,
    create_session,
    open_channel,
    password_token,
    sign_and_encrypt,
)

CLIENTS = 50
SPREAD_S = 1.0
MACHINE = "vmc-1"
VIEWER = ScadaUser("victor", "view-secret-2", "viewer")


async def client_identities(folder: Path, distinct: int) -> list[tuple[str, Path, Path]]:
    """``distinct`` certificates (application URI, certificate, key) sharing one RSA key,
    so that making fifty of them takes a moment rather than fifty key generations."""
    folder.mkdir(parents=True)
    key = folder / "key.pem"
    identities = []
    for index in range(distinct):
        uri = f"urn:burst-test:station-{index}"
        cert = folder / f"station-{index}.der"
        await setup_self_signed_certificate(
            key, cert, uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {}
        )
        identities.append((uri, cert, key))
    return identities


async def read_speed(endpoint: str, uri: str, cert: Path, key: Path, delay_s: float) -> str:
    """One SCADA station: secure session with a password, one read; the status name."""
    await asyncio.sleep(delay_s)
    client = Client(endpoint, timeout=30)
    client.application_uri = uri
    client.set_user(VIEWER.username)
    client.set_password(VIEWER.password)
    await sign_and_encrypt(client, cert, key)
    try:
        async with client:
            ns = await client.get_namespace_index("urn:spindle-gateway:scada")
            node = client.get_node(ua.NodeId(f"{MACHINE}.SpeedRpm", ns))
            await node.read_data_value(raise_on_bad_status=False)
    except ua.UaStatusCodeError as err:
        return ua.StatusCode(err.code).name
    return "Good"


async def server_trusting(
    tmp_path: Path, count: int
) -> tuple[list[tuple[str, Path, Path]], ScadaServer]:
    """``count`` client identities, and a SCADA server (not started) trusting every one."""
    identities = await client_identities(tmp_path / "clients", count)
    pki = tmp_path / "pki"
    (pki / TRUSTED_DIR).mkdir(parents=True)
    for _, cert, _ in identities:
        shutil.copy(cert, pki / TRUSTED_DIR / cert.name)
    settings = ScadaSettings(port=free_tcp_port(), pki_dir=pki, users=(VIEWER,))
    return identities, ScadaServer(settings, [MACHINE], lambda machine, enabled: None)


def burst(tmp_path: Path, distinct: int) -> list[str]:
    """Start a server trusting ``CLIENTS`` certificates; connect ``CLIENTS`` stations at
    once, using the first ``distinct`` of them."""

    async def main() -> list[str]:
        identities, server = await server_trusting(tmp_path, CLIENTS)
        async with server:
            # Within a second, as stations do after a SCADA restart or a network outage.
            stations = [(*identities[i % distinct], i * SPREAD_S / CLIENTS) for i in range(CLIENTS)]
            return list(
                await asyncio.gather(
                    *(read_speed(server.endpoint, *station) for station in stations)
                )
            )

    return asyncio.run(main())


def test_fifty_stations_with_distinct_certificates_are_all_admitted(tmp_path: Path) -> None:
    results = burst(tmp_path, distinct=CLIENTS)
    assert results.count("Good") == CLIENTS, sorted(set(results))


def test_fifty_stations_sharing_one_certificate_are_all_admitted(tmp_path: Path) -> None:
    results = burst(tmp_path, distinct=1)
    assert results.count("Good") == CLIENTS, sorted(set(results))


async def station_channel(endpoint: str, uri: str, cert: Path, key: Path) -> Client:
    """A client with its secure channel open and no session yet (protocol level)."""
    client = Client(endpoint, timeout=30)
    client.application_uri = uri
    await sign_and_encrypt(client, cert, key)
    await open_channel(client)
    return client


def test_a_session_is_activated_while_another_with_its_certificate_is_being_checked(
    tmp_path: Path,
) -> None:
    """The interleaving a burst makes: station A has its session created (certificate
    admitted) and activates it while station B, with the same certificate, is at
    CreateSession and its certificate is being checked against the trust list."""

    async def main() -> list[str]:
        identities, server = await server_trusting(tmp_path, 10)
        statuses = []
        async with server:
            for _ in range(5):
                first = await station_channel(server.endpoint, *identities[0])
                second = await station_channel(server.endpoint, *identities[0])
                try:
                    created = await create_session(first, server.endpoint)
                    checking = asyncio.ensure_future(create_session(second, server.endpoint))
                    await asyncio.sleep(0)  # B's CreateSession is on the wire first
                    statuses.append(await activate(first, created, password_token(VIEWER)))
                    statuses.append(await activate(second, await checking, password_token(VIEWER)))
                finally:
                    first.disconnect_socket()
                    second.disconnect_socket()
        return statuses

    statuses = asyncio.run(main())
    assert statuses == ["Good"] * 10, statuses
