"""The simulated CNC's OPC UA server: FANUC-style content over asyncua.

The gateway talks to a CNC through OPC UA (FOCAS cannot run here), so the
simulated machine needs an OPC UA face that looks like a controller's: spindle
speeds, run mode, machine time, a probe result and the retained custom macro
variables #500–#999, where an external compensation value is handed over.

What is served comes from a :class:`~simulator.link.MachineLink`: ``publish()``
copies ``link.snapshot()`` into the nodes, and a client's write of a macro node
is forwarded to ``link.write_macro()`` inside the write request itself, so the
machine has applied it before the client gets its ``Good``.

This server has no security on purpose (a simulated controller on loopback). The
production gateway's own OPC UA server for SCADA is a separate, secured thing.
See ``simulator/servers/OPCUA.md`` for the address space.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

from asyncua import Node, Server, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.server.address_space import NodeData
from cryptography.x509.oid import ExtendedKeyUsageOID

from drivers.opcua_common import MICROMETRE, RPM, SECOND, ServerLifecycle, data_value, node_id
from simulator.link import MACRO_FIRST, MACRO_LAST, MachineLink, MachineSnapshot

_logger = logging.getLogger(__name__)

DEFAULT_NAMESPACE = "urn:spindle-gateway:simulated-cnc"

# Node ids (strings in the server's namespace) of the machine-state variables.
ACTUAL_SPEED = "Spindle.ActualSpeed"
COMMANDED_SPEED = "Spindle.CommandedSpeed"
RUN_MODE = "Cnc.RunMode"
MACHINE_TIME = "Cnc.MachineTime"
PROBE_ERROR = "Probe.Error"


def _double(value: float) -> ua.Variant:
    return ua.Variant(float(value), ua.VariantType.Double)


def _same(a: float, b: float) -> bool:
    """Equality that treats NaN as equal to NaN (a 'no value' that did not change)."""
    return a == b or (math.isnan(a) and math.isnan(b))


class CncOpcUaServer(ServerLifecycle):
    """An OPC UA server publishing one machine's state and taking macro writes.

    Life cycle: construct (no I/O), ``await start()``, call ``await publish()``
    whenever the machine has moved on, ``await stop()``; or ``async with``.
    """

    def __init__(
        self,
        link: MachineLink,
        *,
        host: str = "127.0.0.1",
        port: int,
        namespace: str = DEFAULT_NAMESPACE,
        macro_range: tuple[int, int] = (MACRO_FIRST, MACRO_LAST),
        secure: tuple[Path, Path] | None = None,
    ) -> None:
        """``secure``: (certificate, private key) of a server that takes Basic256Sha256
        SignAndEncrypt channels only, as a control that requires them (made when
        missing); None: plain TCP."""
        first, last = macro_range
        # The link refuses macros outside #500–#999 (the retained common variables);
        # serving a node whose writes can only fail would be a trap for clients.
        if not MACRO_FIRST <= first <= last <= MACRO_LAST:
            raise ValueError(
                f"macro_range {macro_range} must lie within #{MACRO_FIRST}–#{MACRO_LAST}"
            )
        if not 0 < port < 65536:
            raise ValueError(f"port {port} is not a TCP port")
        self._link = link
        self._host = host
        self._port = port
        self._namespace = namespace
        self._secure = secure
        self._macro_numbers = range(first, last + 1)
        self._server: Server | None = None
        self._ns: int | None = None
        self._nodeids: dict[str, ua.NodeId] = {}
        self._macro_of: dict[ua.NodeId, int] = {}
        # The DataValue publish() is writing right now: the macro setter sees it
        # (synchronously, inside the same call) and must not echo it to the link.
        self._publishing: ua.DataValue | None = None
        # Client-write counter and, per macro, the count at its latest client write;
        # publish() compares them with the count at its snapshot to skip stale values.
        self._client_writes = 0
        self._written_at: dict[int, int] = {}
        # Per macro, the snapshot value object its node was last found or set to by
        # publish(); a client's write drops the entry. The machine keeps a macro's
        # float object until it changes, so an unchanged macro is skipped by identity
        # without reading its node (500 macros a publish).
        self._published: dict[int, float] = {}

    # -- public API ---------------------------------------------------------------

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self._host}:{self._port}/cnc"

    @property
    def namespace_index(self) -> int:
        """Index of the namespace URI in this server's NamespaceArray (after start)."""
        if self._ns is None:
            raise RuntimeError("the namespace index is known only after start()")
        return self._ns

    @staticmethod
    def macro_node_id(n: int) -> str:
        """String node id of custom macro variable #n, e.g. ``Macro.500``."""
        return f"Macro.{n}"

    async def start(self) -> None:
        """Build the address space, publish the first snapshot, then listen."""
        self._refuse_second_start()
        server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("Simulated CNC (spindle-gateway)")
        await server.set_application_uri(f"{self._namespace}:server")
        if self._secure is None:
            # Plain TCP, anonymous only: a simulator on loopback, nothing to protect.
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        else:
            certificate, key = self._secure
            for folder in {certificate.parent, key.parent}:
                folder.mkdir(parents=True, exist_ok=True)
            await setup_self_signed_certificate(
                key,
                certificate,
                f"{self._namespace}:server",
                self._host,
                [ExtendedKeyUsageOID.SERVER_AUTH],
                {"organizationName": "simulated CNC"},
            )
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
            await server.load_certificate(str(certificate))
            await server.load_private_key(str(key))
        server.set_identity_tokens([ua.AnonymousIdentityToken])
        # asyncua maps a user named "admin" to a role that ignores AccessLevel;
        # read-only must stay read-only for every client.
        server.allow_remote_admin(False)
        self._ns = await server.register_namespace(self._namespace)

        async def prepare(server: Server) -> None:
            await self._build_address_space(server)
            await self.publish()

        await self._listen(server, prepare)
        _logger.info("simulated CNC OPC UA server on %s", self.endpoint)

    async def publish(self) -> None:
        """Copy the link's snapshot into the nodes.

        A client's macro write reaches the link before its write returns, so a
        snapshot taken afterwards already holds it. A write that arrives while this
        method is part-way through (it yields between node writes) is newer than the
        snapshot: that macro is skipped here and picked up by the next publish().
        """
        server = self._require_started()
        snap = self._link.snapshot()
        writes_at_snapshot = self._client_writes
        for name, variant in self._state_values(snap):
            await server.write_attribute_value(self._nodeids[name], self._datavalue(variant))
        for number, value in snap.macros.items():
            nodeid = self._nodeids.get(self.macro_node_id(number))
            if nodeid is None:
                continue
            # Check and write happen with no await in between (the store inside
            # write_attribute_value is synchronous), so no client write can slip in.
            if self._written_at.get(number, 0) > writes_at_snapshot:
                continue
            if self._published.get(number) is value:
                continue  # the node holds this value already (no client write since)
            current = server.read_attribute_value(nodeid).Value
            if current is not None and _same(current.Value, float(value)):
                self._published[number] = value
                continue  # unchanged: no needless data-change notification
            datavalue = self._datavalue(_double(value))
            self._publishing = datavalue
            try:
                await server.write_attribute_value(nodeid, datavalue)
            finally:
                self._publishing = None
            if self._written_at.get(number, 0) <= writes_at_snapshot:
                self._published[number] = value

    # -- internals ----------------------------------------------------------------

    @staticmethod
    def _datavalue(variant: ua.Variant) -> ua.DataValue:
        return data_value(variant)

    @staticmethod
    def _state_values(snap: MachineSnapshot) -> list[tuple[str, ua.Variant]]:
        probe = math.nan if snap.probe_error_um is None else snap.probe_error_um
        return [
            (ACTUAL_SPEED, _double(snap.actual_speed_rpm)),
            (COMMANDED_SPEED, _double(snap.commanded_speed_rpm)),
            (RUN_MODE, ua.Variant(int(snap.run_mode), ua.VariantType.Int32)),
            (MACHINE_TIME, _double(snap.time_s)),
            (PROBE_ERROR, _double(probe)),
        ]

    async def _build_address_space(self, server: Server) -> None:
        ns = self.namespace_index

        async def folder(parent: Node, name: str, description: str) -> Node:
            node = await parent.add_object(node_id(name, ns), ua.QualifiedName(name, ns))
            await node.write_attribute(
                ua.AttributeIds.Description,
                data_value(ua.LocalizedText(description), stamped=False),
            )
            return node

        async def variable(
            parent: Node,
            nodeid: str,
            initial: ua.Variant,
            description: str,
            unit: ua.EUInformation | None = None,
        ) -> Node:
            browse_name = nodeid.split(".", 1)[1]
            node = await parent.add_variable(
                node_id(nodeid, ns), ua.QualifiedName(browse_name, ns), initial
            )
            await node.write_attribute(
                ua.AttributeIds.Description,
                data_value(ua.LocalizedText(description), stamped=False),
            )
            if unit is not None:
                await node.add_property(
                    node_id(f"{nodeid}.EngineeringUnits", ns),
                    ua.QualifiedName("EngineeringUnits", 0),
                    ua.Variant(unit, ua.VariantType.ExtensionObject),
                    datatype=node_id(ua.ObjectIds.EUInformation),
                )
            self._nodeids[nodeid] = node.nodeid
            return node

        cnc = await folder(server.nodes.objects, "CNC", "Simulated FANUC-style CNC")
        spindle = await folder(cnc, "Spindle", "Main spindle")
        control = await folder(cnc, "Cnc", "Controller state")
        probe = await folder(cnc, "Probe", "Touch-probe measurement")
        macros = await folder(cnc, "Macros", "Custom macro variables (retained common)")

        zero, nan = _double(0.0), _double(math.nan)
        await variable(spindle, ACTUAL_SPEED, zero, "Actual spindle speed", RPM)
        await variable(spindle, COMMANDED_SPEED, zero, "Commanded spindle speed (S)", RPM)
        await variable(
            control,
            RUN_MODE,
            ua.Variant(0, ua.VariantType.Int32),
            "Run mode: 0 STOP, 1 AUTO, 2 MDI, 3 JOG",
        )
        await variable(control, MACHINE_TIME, zero, "Machine time since start", SECOND)
        await variable(
            probe, PROBE_ERROR, nan, "Last probed Z error (NaN: no measurement)", MICROMETRE
        )

        for number in self._macro_numbers:
            name = self.macro_node_id(number)
            node = await macros.add_variable(
                node_id(name, ns), ua.QualifiedName(f"Macro{number}", ns), zero
            )
            await node.write_attribute(
                ua.AttributeIds.DisplayName,
                data_value(ua.LocalizedText(f"#{number}"), stamped=False),
            )
            await node.set_writable()
            self._nodeids[name] = node.nodeid
            self._macro_of[node.nodeid] = number
            # asyncua calls the setter after its own checks (access level, and the
            # Variant type against the node's Double type: BadTypeMismatch) and in
            # place of storing the value, synchronously within the Write service.
            server.set_attribute_value_setter(node.nodeid, self._set_macro)

    def _set_macro(self, node: NodeData, attr: ua.AttributeIds, value: ua.DataValue) -> None:
        """Store a macro node's new value; a client's value goes to the link first.

        Raising a ``UaStatusCodeError`` here makes asyncua answer the whole Write
        request with that status (a ServiceFault), and the node keeps its old value.
        """
        attval = node.attributes[attr]
        if value is self._publishing:
            attval.value = value
            return
        self._published.pop(self._macro_of[node.nodeid], None)  # a client's write
        variant = value.Value
        if variant is None or variant.VariantType != ua.VariantType.Double:
            # A DataValue without a value, or with a bad StatusCode (asyncua then
            # nulls it): a macro holds a number, so refuse it like a wrong type.
            raise ua.uaerrors.BadTypeMismatch()
        number = self._macro_of[node.nodeid]
        if not math.isfinite(variant.Value):
            raise ua.uaerrors.BadOutOfRange()
        try:
            self._link.write_macro(number, variant.Value)
        except ValueError as err:
            _logger.warning("machine refused #%d = %r: %s", number, variant.Value, err)
            raise ua.uaerrors.BadOutOfRange() from err
        self._client_writes += 1
        self._written_at[number] = self._client_writes
        attval.value = self._datavalue(_double(variant.Value))
