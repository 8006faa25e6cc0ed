"""OPC UA session services called one at a time (CreateSession, ActivateSession), so a
test can interleave them between clients or send a token a polite client would not."""

from __future__ import annotations

import os
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from gateway.scada.server import ScadaUser


async def sign_and_encrypt(client: Client, cert: Path, key: Path) -> None:
    """Basic256Sha256 SignAndEncrypt with the client certificate and key of these files."""
    await client.set_security(
        SecurityPolicyBasic256Sha256,
        str(cert),
        str(key),
        mode=ua.MessageSecurityMode.SignAndEncrypt,
    )


async def open_channel(client: Client) -> None:
    """Connect and open the secure channel, without a session (protocol level)."""
    await client.connect_socket()
    await client.send_hello()
    await client.open_secure_channel()


def password_token(user: ScadaUser) -> ua.UserNameIdentityToken:
    """A user-name token with the password in clear (as over a SignAndEncrypt channel)."""
    return ua.UserNameIdentityToken(
        PolicyId="username", UserName=user.username, Password=user.password.encode()
    )


async def create_session(
    client: Client, endpoint: str, name: str = "station"
) -> ua.CreateSessionResult:
    """CreateSession on the client's open secure channel."""
    params = ua.CreateSessionParameters(
        ClientDescription=ua.ApplicationDescription(
            ApplicationUri=client.application_uri, ApplicationType=ua.ApplicationType.Client
        ),
        EndpointUrl=endpoint,
        SessionName=name,
        ClientNonce=os.urandom(32),
        ClientCertificate=client.security_policy.host_certificate,
        RequestedSessionTimeout=60_000,
    )
    return await client.uaclient.create_session(params)


async def activate(
    client: Client,
    created: ua.CreateSessionResult,
    token: ua.UserNameIdentityToken | ua.AnonymousIdentityToken,
    *,
    signed: bool = True,
) -> str:
    """ActivateSession with ``token`` (signed with the client's key unless ``signed`` is
    False); the status name, "Good" when the session is activated."""
    params = ua.ActivateSessionParameters()
    params.UserIdentityToken = token
    if signed:
        policy = client.security_policy
        params.ClientSignature.Algorithm = policy.AsymmetricSignatureURI
        params.ClientSignature.Signature = policy.asymmetric_cryptography.signature(
            created.ServerCertificate + created.ServerNonce
        )
    try:
        await client.uaclient.activate_session(params)
    except ua.UaStatusCodeError as err:
        return ua.StatusCode(err.code).name
    return "Good"
