"""The CNC over OPC UA (asyncua 2.1): spindle speed, run mode, macro variables.

Real controllers do not standardise their node ids, so every node is a configurable
string id in a namespace given by URI. The namespace index is looked up in the
server's NamespaceArray at every connect: it may change when the server restarts.

asyncua does not rebuild a session reliably after a server restart (asyncua #1660),
and its own auto-reconnect would keep stale node ids. So this driver never reuses a
``Client``: on any link failure it disconnects and drops it, and after the backoff
it connects a new ``Client`` and resolves the namespace again.
"""

from __future__ import annotations

import asyncio
import math
import socket
import struct
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from asyncua import Client, Node, ua
from asyncua.crypto import security_policies
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography.x509.oid import ExtendedKeyUsageOID

from drivers.backoff import Backoff
from drivers.cnc import (
    CncRefusedError,
    GuardedWrite,
    GuardedWrites,
    MacroReads,
    MacroWrite,
    ReconnectingSession,
    SpeedReading,
)
from drivers.opcua_common import node_id

T = TypeVar("T")

DEFAULT_NAMESPACE = "urn:spindle-gateway:simulated-cnc"
#: The types a macro is written as: the one the server holds it in.
WRITABLE_TYPES = (ua.VariantType.Double, ua.VariantType.Float)

#: Status codes with which a working server refuses one request; anything else
#: (session or channel invalid, timeouts, shutdown) means the session is unusable.
_REFUSALS = frozenset(
    {
        ua.StatusCodes.BadNodeIdUnknown,
        ua.StatusCodes.BadNodeIdInvalid,
        ua.StatusCodes.BadAttributeIdInvalid,
        ua.StatusCodes.BadTypeMismatch,
        ua.StatusCodes.BadOutOfRange,
        ua.StatusCodes.BadUserAccessDenied,
        ua.StatusCodes.BadNotWritable,
        ua.StatusCodes.BadNotReadable,
        ua.StatusCodes.BadWriteNotSupported,
        ua.StatusCodes.BadIndexRangeInvalid,
    }
)


#: The security policies the CNC link offers, by the name the configuration uses.
_Policy = (
    type[security_policies.SecurityPolicyBasic256Sha256]
    | type[security_policies.SecurityPolicyAes128Sha256RsaOaep]
    | type[security_policies.SecurityPolicyAes256Sha256RsaPss]
)
SECURITY_POLICIES: dict[str, _Policy] = {
    "Basic256Sha256": security_policies.SecurityPolicyBasic256Sha256,
    "Aes128_Sha256_RsaOaep": security_policies.SecurityPolicyAes128Sha256RsaOaep,
    "Aes256_Sha256_RsaPss": security_policies.SecurityPolicyAes256Sha256RsaPss,
}
SECURITY_MODES = {
    "Sign": ua.MessageSecurityMode.Sign,
    "SignAndEncrypt": ua.MessageSecurityMode.SignAndEncrypt,
}


@dataclass(frozen=True)
class OpcUaSecurity:
    """A signed, and by default encrypted, channel to the CNC.

    ``certificate`` and ``private_key``: the gateway's own, made on the first connect
    when neither file exists (self-signed, for the CNC's trust list; an engineer copies
    ``certificate`` there once). ``server_certificate``: the CNC's certificate, pinned;
    None takes the one the CNC's endpoint list presents.
    """

    certificate: Path
    private_key: Path
    policy: str = "Basic256Sha256"
    mode: str = "SignAndEncrypt"
    server_certificate: Path | None = None

    def __post_init__(self) -> None:
        if self.policy not in SECURITY_POLICIES:
            raise ValueError(f"policy {self.policy!r}: expected one of {list(SECURITY_POLICIES)}")
        if self.mode not in SECURITY_MODES:
            raise ValueError(f"mode {self.mode!r}: expected one of {list(SECURITY_MODES)}")


@dataclass
class _Session:
    """One connected asyncua Client and the node ids resolved for it."""

    client: Client
    namespace_index: int
    speed: Node
    commanded: Node
    run_mode: Node | None
    macros: dict[int, Node] = field(default_factory=dict)
    #: The variant type each macro's value has on this server (learned from a read).
    macro_types: dict[int, ua.VariantType] = field(default_factory=dict)


class OpcUaCnc(ReconnectingSession[_Session]):
    """A CNC reached over OPC UA; implements :class:`drivers.cnc.CncClient`.

    ``macro_node`` is a template with ``{n}`` for the macro number. Connects on the
    first call; ``timeout_s`` bounds each request (a connect: three times that).
    """

    link_errors = (OSError, TimeoutError, ua.UaError)

    def __init__(
        self,
        endpoint: str,
        namespace: str = DEFAULT_NAMESPACE,
        speed_node: str = "Spindle.ActualSpeed",
        commanded_node: str = "Spindle.CommandedSpeed",
        run_mode_node: str | None = "Cnc.RunMode",
        macro_node: str = "Macro.{n}",
        timeout_s: float = 2.0,
        username: str | None = None,
        password: str | None = None,
        security: OpcUaSecurity | None = None,
        *,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if "{n}" not in macro_node:
            raise ValueError(f"macro_node must contain '{{n}}', got {macro_node!r}")
        super().__init__(f"OPC UA {endpoint}", timeout_s=timeout_s, backoff=backoff, clock=clock)
        self.endpoint = endpoint
        self.namespace = namespace
        self._speed_node = speed_node
        self._commanded_node = commanded_node
        self._run_mode_node = run_mode_node
        self._macro_node = macro_node
        self._username = username
        self._password = password
        self._security = security

    @property
    def namespace_index(self) -> int | None:
        """Index of ``namespace`` on the connected server; None while not connected."""
        return self._session.namespace_index if self._session is not None else None

    # -- CncClient ----------------------------------------------------------------

    async def read_speed(self) -> SpeedReading:
        """Actual and commanded speed and run mode, in one Read request."""

        async def read(session: _Session) -> SpeedReading:
            nodes = [session.speed, session.commanded]
            if session.run_mode is not None:
                nodes.append(session.run_mode)
            values = await session.client.read_attributes(nodes)
            actual = _number(values[0], self._speed_node)
            commanded = _number(values[1], self._commanded_node)
            run_mode = None
            if session.run_mode is not None:
                run_mode = int(_number(values[2], str(self._run_mode_node)))
            return SpeedReading(actual_rpm=actual, commanded_rpm=commanded, run_mode=run_mode)

        return await self._call("reading spindle speed", _refusals_as_cnc(read))

    async def write_macro(self, number: int, value: float) -> None:
        """Write macro #number as the type the CNC holds it in: Double, or Float where a
        server (a PLC gateway, some controls' user variables) declares it so and would
        answer a Double with ``BadTypeMismatch``. The type is learned from a read of the
        macro (the loop reads it every cycle; otherwise one Read first). A macro held as
        an integer or text is refused here, naming its type: a rounded offset is not one
        the loop decided.

        A non-finite value raises ``ValueError`` before any I/O: a NaN must never
        reach a machine offset.
        """
        _check_finite(number, value)

        async def write(session: _Session) -> None:
            if number not in session.macro_types:
                _learn_type(session, number, await self._macro(session, number).read_data_value())
            await self._write_on(session, number, value)

        await self._call(
            f"writing macro #{number} ({self._macro_id(number)})", _refusals_as_cnc(write)
        )

    async def read_macro(self, number: int) -> float:
        """Read macro #number back from the controller."""
        return await self._call(
            f"reading macro #{number} ({self._macro_id(number)})",
            _refusals_as_cnc(lambda session: self._read_on(session, number)),
        )

    async def read_macros(self, numbers: Sequence[int]) -> MacroReads:
        """Macros #numbers in one Read request (one ReadValueId a node). A node the server
        answers with a refusal status (unknown node, not readable) or a value that is not
        a number is that macro's :class:`CncRefusedError` alone; each type read is
        remembered for writes, as :meth:`read_macro` does."""
        wanted = list(dict.fromkeys(numbers))

        async def read(session: _Session) -> MacroReads:
            nodes = [self._macro(session, number) for number in wanted]
            datavalues = await session.client.read_attributes(nodes)
            results: MacroReads = {}
            for number, datavalue in zip(wanted, datavalues, strict=True):
                try:
                    results[number] = _number(datavalue, self._macro_id(number))
                except CncRefusedError as exc:
                    results[number] = CncRefusedError(
                        f"{self._where}: reading macro #{number} refused: {exc}"
                    )
                    continue
                _learn_type(session, number, datavalue)
            return results

        listed = ", ".join(f"#{number}" for number in wanted)
        return await self._call(f"reading macros {listed}", _refusals_as_cnc(read))

    async def write_macro_if(
        self, number: int, value: float, holds: Callable[[float], bool]
    ) -> GuardedWrite:
        """Read macro #number, then, only if ``holds(read)``, write ``value`` in the same
        session; nothing else is awaited between the Read's response and the Write
        request (OPC UA has no conditional write: that gap is what remains). The read
        also gives the type the value is written as."""
        _check_finite(number, value)

        async def read_then_write(session: _Session) -> GuardedWrite:
            held = await self._read_on(session, number)
            if not holds(held):
                return GuardedWrite(held, written=False)
            await self._write_on(session, number, value)
            return GuardedWrite(held, written=True)

        return await self._call(
            f"checking and writing macro #{number} ({self._macro_id(number)})",
            _refusals_as_cnc(read_then_write),
        )

    async def write_macros_if(self, writes: Sequence[MacroWrite]) -> GuardedWrites:
        """One Read of every macro, then one Write of those whose read holds, in the same
        session with nothing awaited between the Read's response and the Write request (as
        :meth:`write_macro_if`, for several macros at once). A node refused on the read or
        on the write (its own status code) is that macro's :class:`CncRefusedError`."""
        for write in writes:
            _check_finite(write.number, write.value)

        async def read_then_write(session: _Session) -> GuardedWrites:
            nodes = [self._macro(session, write.number) for write in writes]
            datavalues = await session.client.read_attributes(nodes)
            results: GuardedWrites = {}
            ready: list[tuple[MacroWrite, float, ua.DataValue]] = []
            for write, datavalue in zip(writes, datavalues, strict=True):
                try:
                    held = _number(datavalue, self._macro_id(write.number))
                    _learn_type(session, write.number, datavalue)
                    if not write.holds(held):
                        results[write.number] = GuardedWrite(held, written=False)
                        continue
                    ready.append((write, held, self._datavalue(session, write.number, write.value)))
                except CncRefusedError as exc:
                    results[write.number] = self._write_refused(write.number, str(exc))
            if ready:
                await self._write_ready(session, ready, results)
            return {write.number: results[write.number] for write in writes}

        listed = ", ".join(f"#{write.number}" for write in writes)
        return await self._call(
            f"checking and writing macros {listed}", _refusals_as_cnc(read_then_write)
        )

    async def _write_ready(
        self,
        session: _Session,
        ready: list[tuple[MacroWrite, float, ua.DataValue]],
        results: GuardedWrites,
    ) -> None:
        """One Write of every macro whose read held; each node's status is its outcome. A
        server that answers one node's refusal with a fault of the whole request may have
        written the nodes before it: each macro is then read again and written on its own
        (:meth:`_write_again`), so the refused one fails alone."""
        nodeids = [self._macro(session, write.number).nodeid for write, _, _ in ready]
        try:
            statuses = await session.client.uaclient.write_attributes(
                nodeids, [datavalue for _, _, datavalue in ready]
            )
        except ua.UaStatusCodeError as exc:
            if exc.code not in _REFUSALS:
                raise
            for write, held, datavalue in ready:
                results[write.number] = await self._write_again(session, write, held, datavalue)
            return
        for (write, held, _), status in zip(ready, statuses, strict=True):
            if status.is_good():
                results[write.number] = GuardedWrite(held, written=True)
            elif status.value in _REFUSALS:
                results[write.number] = self._write_refused(write.number, status.name)
            else:
                raise ua.UaStatusCodeError(status.value)

    async def _write_again(
        self, session: _Session, write: MacroWrite, held: float, datavalue: ua.DataValue
    ) -> GuardedWrite | CncRefusedError:
        """After a refused Write of several macros: this macro read again, and written only
        if the read holds. One that moved from what it held to the value sent was written
        by that Write; one that held the value sent already is written again (its
        refusal, if it is the refused one, is its own failure)."""
        try:
            now = await self._read_on(session, write.number)
            sent = _as_held(datavalue)
            if now == sent and held != sent:
                return GuardedWrite(held, written=True)
            if not write.holds(now):
                return GuardedWrite(now, written=False)
            await self._write_on(session, write.number, write.value)
        except CncRefusedError as exc:
            return self._write_refused(write.number, str(exc))
        except ua.UaStatusCodeError as exc:
            if exc.code not in _REFUSALS:
                raise
            return self._write_refused(write.number, ua.StatusCode(exc.code).name)
        return GuardedWrite(now, written=True)

    def _write_refused(self, number: int, why: str) -> CncRefusedError:
        return CncRefusedError(
            f"{self._where}: checking and writing macro #{number} ({self._macro_id(number)}) "
            f"refused: {why}"
        )

    async def _read_on(self, session: _Session, number: int) -> float:
        """One Read of macro #number's value; its type is remembered for writes."""
        datavalue = await self._macro(session, number).read_data_value()
        value = _number(datavalue, self._macro_id(number))
        _learn_type(session, number, datavalue)
        return value

    async def _write_on(self, session: _Session, number: int, value: float) -> None:
        """One Write of macro #number as the type learned from a read of it."""
        datavalue = self._datavalue(session, number, value)
        await self._macro(session, number).write_value(datavalue)

    def _datavalue(self, session: _Session, number: int, value: float) -> ua.DataValue:
        """``value`` as the type learned from a read of macro #number (a Double or Float)."""
        vtype = session.macro_types[number]
        if vtype not in WRITABLE_TYPES:
            raise CncRefusedError(
                f"{self._macro_id(number)} holds a {vtype.name}; the compensation writes "
                "a Double or a Float"
            )
        return ua.DataValue(ua.Variant(float(value), vtype))

    # -- session life cycle ---------------------------------------------------------

    async def _open(self) -> _Session:
        client = Client(self.endpoint, timeout=self._timeout_s)
        if self._security is not None:
            await _secure(client, self._security)
        if self._username is not None:
            client.set_user(self._username)
        if self._password is not None:
            client.set_password(self._password)
        connected = False
        try:
            await client.connect()
            connected = True
            namespaces = await client.get_namespace_array()
            if self.namespace not in namespaces:
                raise ConnectionError(
                    f"namespace {self.namespace!r} is not on the server (it has {namespaces})"
                )
            ns = namespaces.index(self.namespace)
        except BaseException:
            # Also on cancellation (the connect timeout): never leave a socket or
            # asyncua's supervisor tasks behind.
            if connected:
                await _disconnect_quietly(client, self._timeout_s)
            else:
                client.disconnect_socket()
            raise

        def node(identifier: str) -> Node:
            return client.get_node(node_id(identifier, ns))

        return _Session(
            client=client,
            namespace_index=ns,
            speed=node(self._speed_node),
            commanded=node(self._commanded_node),
            run_mode=node(self._run_mode_node) if self._run_mode_node is not None else None,
        )

    async def _discard(self, session: _Session) -> None:
        await _disconnect_quietly(session.client, self._timeout_s)

    def _macro_id(self, number: int) -> str:
        """String node id of macro #number, e.g. ``Macro.500``."""
        return self._macro_node.format(n=number)

    def _macro(self, session: _Session, number: int) -> Node:
        node = session.macros.get(number)
        if node is None:
            nodeid = node_id(self._macro_id(number), session.namespace_index)
            node = session.macros[number] = session.client.get_node(nodeid)
        return node


def _refusals_as_cnc(
    operation: Callable[[_Session], Awaitable[T]],
) -> Callable[[_Session], Awaitable[T]]:
    """Turn a server's refusal of one request into :class:`CncRefusedError` (link kept)."""

    async def run(session: _Session) -> T:
        try:
            return await operation(session)
        except ua.UaStatusCodeError as exc:
            if exc.code in _REFUSALS:
                raise CncRefusedError(ua.StatusCode(exc.code).name) from exc
            raise

    return run


async def _secure(client: Client, security: OpcUaSecurity) -> None:
    """Set the client's certificate, key, policy and mode; make the certificate and key
    on first use. Its application URI is the client's, as the CNC checks it."""
    if not security.certificate.exists() and not security.private_key.exists():
        security.certificate.parent.mkdir(parents=True, exist_ok=True)
        security.private_key.parent.mkdir(parents=True, exist_ok=True)
        await setup_self_signed_certificate(
            security.private_key,
            security.certificate,
            client.application_uri,
            socket.gethostname(),
            [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"organizationName": "spindle-gateway"},
        )
        security.private_key.chmod(0o600)
    await client.set_security(
        SECURITY_POLICIES[security.policy],
        str(security.certificate),
        str(security.private_key),
        server_certificate=(
            None if security.server_certificate is None else str(security.server_certificate)
        ),
        mode=SECURITY_MODES[security.mode],
    )


def _check_finite(number: int, value: float) -> None:
    """A NaN or inf must never reach a machine offset: refused before any I/O."""
    if not math.isfinite(value):
        raise ValueError(f"macro #{number}: refusing to write non-finite value {value!r}")


def _learn_type(session: _Session, number: int, datavalue: ua.DataValue) -> None:
    """Remember the variant type of macro #number's value (Double when it has none)."""
    variant = datavalue.Value
    if variant is not None and variant.Value is not None:
        session.macro_types[number] = variant.VariantType
    else:
        session.macro_types[number] = ua.VariantType.Double


def _as_held(datavalue: ua.DataValue) -> float:
    """The value of a DataValue to write as the server holds it (a Float: float32)."""
    variant = datavalue.Value
    assert variant is not None
    value = float(variant.Value)
    if variant.VariantType == ua.VariantType.Float:
        return float(struct.unpack("<f", struct.pack("<f", value))[0])
    return value


def _number(datavalue: ua.DataValue, node: str) -> float:
    """The numeric value of a read result, or :class:`CncRefusedError` naming the node."""
    status = datavalue.StatusCode
    if status is not None and not status.is_good():
        if status.value in _REFUSALS:
            raise CncRefusedError(f"{node}: {status.name}")
        raise ua.UaStatusCodeError(status.value)
    variant = datavalue.Value
    value = variant.Value if variant is not None else None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise CncRefusedError(f"{node}: not a number ({value!r})")
    return float(value)


async def _disconnect_quietly(client: Client, timeout_s: float) -> None:
    """Close session, channel and socket; on a dead link this only stops the tasks."""
    try:
        await asyncio.wait_for(client.disconnect(), timeout_s)
    except (OSError, TimeoutError, ua.UaError):
        client.disconnect_socket()
