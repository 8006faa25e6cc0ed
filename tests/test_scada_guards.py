"""The SCADA server's guards against a hostile network: password guessing, certificate floods.

Real ScadaServers on loopback with their own PKI in a temporary folder, real
clients: asyncua's ``Client`` (as a SCADA written in Python would connect) and
node-opcua (``tests/node/scada_client.mjs``, an independent stack). Lockout
durations run on a manual clock, so the tests never wait them out.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.x509.oid import ExtendedKeyUsageOID

from drivers.clock import ManualClock
from gateway.scada.login_throttle import LoginThrottle, ThrottlePolicy
from gateway.scada.server import REJECTED_DIR, TRUSTED_DIR, ScadaServer, ScadaSettings
from tests.test_scada import MACHINE, NODE_DIR, OPERATOR, VIEWER, node_client, settings
from tests.ua_session import sign_and_encrypt

POLICY = ThrottlePolicy(max_failures=5, window_s=60.0, lockout_s=30.0, max_lockout_s=120.0)


@pytest.fixture(scope="module")
def node_pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("node") is None or not (NODE_DIR / "node_modules").is_dir():
        raise RuntimeError("node and tests/node/node_modules are needed (npm ci in tests/node)")
    return tmp_path_factory.mktemp("node-pki")


def serve(
    scada_settings: ScadaSettings,
    scenario: Callable[[ScadaServer], Awaitable[None]],
    clock: ManualClock | None = None,
) -> None:
    async def main() -> None:
        now = clock.now if clock is not None else time.monotonic
        server = ScadaServer(scada_settings, [MACHINE], lambda m, e: None, clock=now)
        async with server:
            await scenario(server)

    asyncio.run(main())


async def client_certificate(folder: Path) -> tuple[Path, Path]:
    """A fresh self-signed client certificate (what a new SCADA installation presents)."""
    folder.mkdir(parents=True, exist_ok=True)
    cert, key = folder / "client_cert.der", folder / "client_key.pem"
    await setup_self_signed_certificate(
        key,
        cert,
        Client("opc.tcp://127.0.0.1:1").application_uri,
        "localhost",
        [ExtendedKeyUsageOID.CLIENT_AUTH],
        {},
    )
    return cert, key


async def login(server: ScadaServer, cert: tuple[Path, Path], username: str, password: str) -> str:
    """Connect with asyncua's client over SignAndEncrypt; the session's status name."""
    client = Client(server.endpoint, timeout=10)
    await sign_and_encrypt(client, cert[0], cert[1])
    client.set_user(username)
    client.set_password(password)
    try:
        await client.connect()
    except ua.UaStatusCodeError as err:
        return ua.StatusCode(err.code).name
    await client.disconnect()
    return "Good"


def lockout_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if "locked for" in r.getMessage()]


def test_lockout_refuses_even_the_right_password_then_recovers_and_grows(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.scada.server")
    clock = ManualClock(1000.0)

    async def scenario(server: ScadaServer) -> None:
        cert = await client_certificate(tmp_path / "client")
        right = OPERATOR.password
        assert await login(server, cert, OPERATOR.username, right) == "Good"
        for _ in range(5):
            assert await login(server, cert, OPERATOR.username, "guess") == "BadUserAccessDenied"
        assert server.login_throttle.checked == 6
        # Locked: the right password is refused unchecked; another user from the same
        # address is not locked out by alice's failures.
        assert await login(server, cert, OPERATOR.username, right) == "BadUserAccessDenied"
        assert await login(server, cert, VIEWER.username, VIEWER.password) == "Good"
        assert server.login_throttle.checked == 7 and server.login_throttle.refused_locked == 1
        lines = lockout_lines(caplog)
        assert lines == [
            "SCADA logins as user 'alice' locked for 30 s after 5 failed attempts "
            "within 60 s; every login through it is refused until then",
        ]
        clock.advance(29.0)  # 29 s after the 5th failure: still locked
        assert await login(server, cert, OPERATOR.username, right) == "BadUserAccessDenied"
        clock.advance(1.0)
        assert await login(server, cert, OPERATOR.username, right) == "Good"
        # A success clears the count, but a second burst of failures locks for longer.
        for _ in range(5):
            assert await login(server, cert, OPERATOR.username, "guess") == "BadUserAccessDenied"
        assert "locked for 30 s" in lockout_lines(caplog)[-1]  # cleared by the success
        checked = server.login_throttle.checked
        for _ in range(5):  # refused unchecked: they neither count nor extend the lockout
            assert await login(server, cert, OPERATOR.username, "guess") == "BadUserAccessDenied"
        assert server.login_throttle.checked == checked
        clock.advance(30.0)
        for _ in range(5):
            assert await login(server, cert, OPERATOR.username, "guess") == "BadUserAccessDenied"
        assert "locked for 60 s" in lockout_lines(caplog)[-1]
        clock.advance(59.0)
        assert await login(server, cert, OPERATOR.username, right) == "BadUserAccessDenied"
        clock.advance(1.0)
        assert await login(server, cert, OPERATOR.username, right) == "Good"

    serve(settings(tmp_path / "pki", login_throttle=POLICY), scenario, clock)
    assert len(lockout_lines(caplog)) == 3  # once per lockout of the user (one user failed)


def test_password_guessing_rate_is_cut_to_the_lockout(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """50 wrong passwords as fast as a client can, then the right one: it is refused."""
    caplog.set_level(logging.WARNING, logger="gateway.scada.server")
    figures: dict[str, float] = {}

    async def scenario(server: ScadaServer) -> None:
        cert = await client_certificate(tmp_path / "client")
        start = time.monotonic()
        for k in range(50):
            status = await login(server, cert, OPERATOR.username, f"guess-{k}")
            assert status == "BadUserAccessDenied"
        elapsed_s = time.monotonic() - start
        figures["attempts_per_s"] = 50 / elapsed_s
        figures["checked_per_s"] = server.login_throttle.checked / elapsed_s
        figures["elapsed_s"] = elapsed_s
        assert await login(server, cert, OPERATOR.username, OPERATOR.password) == (
            "BadUserAccessDenied"
        )
        figures["checked"] = server.login_throttle.checked

    serve(settings(tmp_path / "pki"), scenario)  # the default policy, the wall clock
    print(figures)
    assert figures["elapsed_s"] < 30.0  # the whole burst fell inside the first lockout
    assert figures["checked"] == 5  # only five of the 51 passwords were ever compared
    assert figures["attempts_per_s"] > 2.0
    # The same bound in whole numbers (both rates share one elapsed time): at most one
    # password in ten of the 50 is compared; as rates, 5/t vs 50/t/10 tied in floating point.
    assert figures["checked"] * 10 <= 50
    assert len(lockout_lines(caplog)) == 1  # the user; one user's failures leave the address


def test_node_opcua_client_is_locked_out_too(tmp_path: Path, node_pki: Path) -> None:
    clock = ManualClock()
    policy = ThrottlePolicy(max_failures=3, window_s=60.0, lockout_s=30.0)

    async def scenario(server: ScadaServer) -> None:
        read = [{"read": f"{MACHINE}.SpeedRpm"}]
        code, reply = await node_client(server, read, node_pki, user=OPERATOR, password="x")
        assert code == 1 and reply["status"] == "BadUserAccessDenied", reply
        cert = await client_certificate(tmp_path / "client")
        for _ in range(2):  # the rest of the burst from another client on the same host
            assert await login(server, cert, OPERATOR.username, "y") == "BadUserAccessDenied"
        code, reply = await node_client(server, read, node_pki, user=OPERATOR)
        assert code == 1 and reply["status"] == "BadUserAccessDenied", reply
        clock.advance(30.0)
        code, reply = await node_client(server, read, node_pki, user=OPERATOR)
        assert code == 0, reply

    serve(settings(tmp_path / "pki", login_throttle=policy), scenario, clock)


def thumbprint(cert_file: Path) -> str:
    return x509.load_der_x509_certificate(cert_file.read_bytes()).fingerprint(hashes.SHA1()).hex()


def test_twenty_fresh_certificates_leave_the_newest_k_and_one_line_each(
    tmp_path: Path, node_pki: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    pki = tmp_path / "pki"
    keep = 5

    async def scenario(server: ScadaServer) -> None:
        # One trusted client, so every refusal goes through asyncua's trust store
        # (whose own logging of a refusal is a traceback).
        trusted = await client_certificate(tmp_path / "trusted-client")
        shutil.copy(trusted[0], pki / TRUSTED_DIR / "hmi.der")
        assert await login(server, trusted, VIEWER.username, VIEWER.password) == "Good"
        caplog.clear()
        thumbprints = []
        for k in range(19):
            cert = await client_certificate(tmp_path / f"fresh-{k}")
            assert await login(server, cert, VIEWER.username, VIEWER.password) == (
                "BadCertificateUntrusted"
            )
            thumbprints.append(thumbprint(cert[0]))
        # The 20th: node-opcua, with a new PKI (a new certificate).
        read = [{"read": f"{MACHINE}.SpeedRpm"}]
        code, reply = await node_client(server, read, tmp_path / "node", user=VIEWER)
        assert code == 1 and reply["status"] == "BadCertificateUntrusted", reply
        pem = x509.load_pem_x509_certificate(Path(reply["certificate"]).read_bytes())
        thumbprints.append(pem.fingerprint(hashes.SHA1()).hex())
        files = sorted((pki / REJECTED_DIR).glob("*.der"))
        assert len(files) == keep
        assert {f.stem.rsplit("_", 1)[1] for f in files} == set(thumbprints[-keep:])
        # The trusted client still gets in after the flood.
        assert await login(server, trusted, VIEWER.username, VIEWER.password) == "Good"

    serve(settings(pki, trust_all_clients=False, rejected_keep=keep), scenario)
    ours = [r for r in caplog.records if not r.name.startswith("asyncua")]
    refusals = [r for r in ours if "refused: certificate not trusted" in r.getMessage()]
    assert len(refusals) == 20
    assert [r for r in ours if r not in refusals and r.levelno >= logging.WARNING] == []
    assert sum("older rejected certificate(s) removed" in r.getMessage() for r in refusals) == 15
    assert [r for r in caplog.records if r.exc_info] == []  # no traceback anywhere
    assert "Traceback" not in caplog.text


def test_throttle_keys_address_and_user_separately() -> None:
    clock = ManualClock()
    throttle = LoginThrottle(POLICY, clock.now)
    alice_here = [("address", "10.0.0.1"), ("user", "alice")]
    alice_there = [("address", "10.0.0.2"), ("user", "alice")]
    bob_there = [("address", "10.0.0.2"), ("user", "bob")]
    for _ in range(2):
        assert throttle.failed(alice_here) == []
    for _ in range(2):
        assert throttle.failed(alice_there) == []
    started = throttle.failed(alice_there)  # alice's 5th failure, from a second address
    assert [lock.key for lock in started] == [("user", "alice")]
    assert throttle.locked_for_s(alice_here) == 30.0
    assert throttle.locked_for_s(bob_there) == 0.0  # that address failed only 3 times
    clock.advance(61.0)  # failures older than the window no longer count
    for _ in range(4):
        throttle.failed(bob_there)
    assert throttle.locked_for_s(bob_there) == 0.0
    clock.advance(3600.0 + 1.0)
    assert [lock.duration_s for lock in throttle.failed(alice_here)] == []
    for _ in range(4):
        locks = throttle.failed(alice_here)
    assert {lock.duration_s for lock in locks} == {30.0}  # forgotten after an idle hour
    with pytest.raises(ValueError):
        ThrottlePolicy(lockout_s=60.0, max_lockout_s=30.0)
    with pytest.raises(ValueError):
        ThrottlePolicy(max_failures=0)


def test_an_address_is_locked_by_many_users_failures_not_by_one_users() -> None:
    """One user failing five times from an address locks that user only; failures naming
    five users from one address (one client trying account after account) lock it."""
    clock = ManualClock()
    throttle = LoginThrottle(POLICY, clock.now)
    here = ("address", "10.0.0.1")
    for _ in range(5):
        started = throttle.failed([here, ("user", "alice")])
    assert [lock.key for lock in started] == [("user", "alice")]
    assert throttle.locked_for_s([here, ("user", "alice")]) == 30.0
    assert throttle.locked_for_s([here, ("user", "bob")]) == 0.0  # bob still logs in here
    throttle.succeeded([here, ("user", "bob")])
    for name in ("carol", "dave", "erin"):
        assert throttle.failed([here, ("user", name)]) == []
    started = throttle.failed([here, ("user", "frank")])  # the fifth user failing here
    assert [(lock.key, lock.failures) for lock in started] == [(here, 9)]
    assert throttle.locked_for_s([here, ("user", "bob")]) == 30.0
    assert throttle.locked_for_s([("address", "10.0.0.2"), ("user", "bob")]) == 0.0
    # A success takes its own user's failures off the address, and only those.
    clock.advance(61.0)
    other = ("address", "10.0.0.3")
    for name in ("carol", "dave", "erin", "frank"):
        throttle.failed([other, ("user", name)])
    throttle.succeeded([other, ("user", "frank")])
    assert throttle.failed([other, ("user", "gina")]) == []  # 4 users failed, not 5
    assert [lock.key for lock in throttle.failed([other, ("user", "hal")])] == [other]


def test_config_keys_load_and_bad_bounds_are_located(tmp_path: Path) -> None:
    from gateway.config import load_config
    from tests.test_config import GOOD, refusal, write_config

    scada = (
        "scada:\n  port: 4999\n  pki_dir: PKI\n  rejected_keep: 7\n"
        "  login_max_failures: 3\n  login_lockout_s: 10\n  login_max_lockout_s: 40\n"
    ).replace("PKI", str(tmp_path / "pki"))
    state = f"state_dir: {tmp_path / 'state'}\nlogging:\n  local_store: {tmp_path / 'p.sqlite'}\n"
    path = write_config(tmp_path, tmp_path / "store", GOOD + state + scada)
    section = load_config(path).scada
    assert section is not None and section.rejected_keep == 7
    assert (section.login_max_failures, section.login_window_s) == (3, 60.0)
    bad = write_config(tmp_path, tmp_path / "store", GOOD + scada.replace("40", "5"))
    assert refusal(bad) == (
        f"{bad}:21: scada: login_lockout_s (10.0) must not exceed login_max_lockout_s (5.0)"
    )
