"""The gateway's OPC UA server for the plant's SCADA: live values out, one switch in.

Per machine, SCADA reads what the compensation loop measured and decided (the
temperatures with their quality, speed, regime, model, predicted and applied
compensation, health counters) and may switch the compensation on or off. The
address space, units and examples are in ``docs/scada.md``.

Security (asyncua's defaults are open, so every layer is set explicitly):

* one endpoint, Basic256Sha256 SignAndEncrypt; no ``None`` endpoint. asyncua
  still answers GetEndpoints on an unsecured channel (discovery needs that), but
  a session on such a channel is never activated: the user manager requires the
  client certificate of the secure channel;
* client certificates: a self-signed server certificate is created in
  ``pki_dir`` on first start and reused afterwards. A client's certificate must
  be in ``pki_dir/trusted`` (``.der`` or ``.pem``; checked at every
  CreateSession, so copying one there needs no restart) unless
  ``trust_all_clients``; an untrusted one is refused (BadCertificateUntrusted) and
  saved in ``pki_dir/rejected`` for an engineer to review and move (the newest
  ``rejected_keep`` only, so a stream of fresh certificates cannot fill the disk),
  with one log line and no traceback;
* identity: user name and password checked against :class:`ScadaUser` (constant-
  time compare); anonymous only if ``allow_anonymous``, and then read-only.
  Failed logins lock the user name out for a while, and the remote address when it
  fails many users (:mod:`gateway.scada.login_throttle`), so passwords cannot be
  guessed at speed;
* authorisation: only operators may send Write requests (viewers and anonymous
  get BadUserAccessDenied and nothing changes); the only writable node is each
  machine's ``CompensationEnabled``. An operator's write calls
  ``on_enable(machine, enabled)`` inside the Write service: the client's ``Good``
  means the gateway has taken it.

Life cycle: construct (no I/O), ``await start()``, ``await publish(record,
health)`` after every cycle (or ``publish_soon`` from a synchronous sink),
``await stop()``; or ``async with``.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import math
import re
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from asyncua import Node, Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.address_space import NodeData
from asyncua.server.user_managers import UserManager
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from drivers.opcua_common import (
    CELSIUS,
    MICROMETRE,
    RPM,
    ServerLifecycle,
    data_value,
    node_id,
    status_code,
    ua_datetime,
)
from gateway.live.record import AxisRecord, CycleRecord
from gateway.scada.login_throttle import Key, LoginThrottle, ThrottlePolicy
from gateway.scada.trust_store import TolerantTrustStore

_logger = logging.getLogger(__name__)

NAMESPACE = "urn:spindle-gateway:scada"

SERVER_CERT = "server_cert.der"
SERVER_KEY = "server_key.pem"
TRUSTED_DIR = "trusted"
REJECTED_DIR = "rejected"
CRL_DIR = "crl"

# -- settings -------------------------------------------------------------------------


@dataclass(frozen=True)
class ScadaUser:
    """A SCADA account: operators may switch compensation on/off, viewers only read."""

    username: str
    password: str = field(repr=False)
    role: Literal["operator", "viewer"]

    def __post_init__(self) -> None:
        if not self.username:
            raise ValueError("username must not be empty")
        if not self.password:
            raise ValueError(f"user {self.username!r} needs a password")
        if self.role not in ("operator", "viewer"):
            raise ValueError(f"role of {self.username!r} must be 'operator' or 'viewer'")


@dataclass(frozen=True, kw_only=True)
class ScadaSettings:
    """Where and how the SCADA server listens (see the module docstring for security).

    ``pki_dir`` keeps the server certificate (``server_cert.der``) and key
    (``server_key.pem``), the trusted client certificates (``trusted/``), refused
    ones (``rejected/``, the newest ``rejected_keep``) and optional revocation
    lists (``crl/``). ``login_throttle``: when failed logins lock a client out.
    """

    port: int
    pki_dir: Path
    users: tuple[ScadaUser, ...] = ()
    host: str = "127.0.0.1"
    allow_anonymous: bool = False
    application_uri: str = NAMESPACE
    trust_all_clients: bool = False
    rejected_keep: int = 50
    login_throttle: ThrottlePolicy = field(default_factory=ThrottlePolicy)

    def __post_init__(self) -> None:
        if not 0 < self.port < 65536:
            raise ValueError(f"port {self.port} is not a TCP port")
        if self.rejected_keep < 1:
            raise ValueError(f"rejected_keep must be at least 1, got {self.rejected_keep}")
        object.__setattr__(self, "pki_dir", Path(self.pki_dir))
        object.__setattr__(self, "users", tuple(self.users))
        names = [u.username for u in self.users]
        if len(set(names)) != len(names):
            raise ValueError(f"user names must be unique, got {names}")


#: ``health`` keys published as UInt32 counters under ``Machines/<id>/Health``.
HEALTH_COUNTERS = {
    "failed_writes": ("Health.FailedWrites", "CNC writes that failed"),
    "cycles": ("Health.Cycles", "Cycles run since start"),
    "external_changes": (
        "Health.ExternalChanges",
        "Changes of the macro the gateway did not make",
    ),
    "link_errors_total": ("Health.LinkErrorsTotal", "Link errors since start, all cycles"),
    "sink_failures": ("Health.SinkFailures", "Record deliveries (log, SCADA) that failed"),
    "loop_restarts": ("Health.LoopRestarts", "Restarts of the machine loop after a failure"),
    "forwarder_backlog": ("Health.ForwarderBacklog", "Points buffered for InfluxDB"),
    "dropped_points": ("Health.DroppedPoints", "Points dropped from a full buffer"),
    "rejected_points": ("Health.RejectedPoints", "Points InfluxDB refused as invalid"),
    "forwarder_restarts": (
        "Health.ForwarderRestarts",
        "Restarts of the InfluxDB forwarder after a failure",
    ),
    "model_swaps": ("Health.ModelSwaps", "Promoted model sets taken into the bank"),
    "model_swaps_refused": (
        "Health.ModelSwapsRefused",
        "Promoted models refused by the machine's checks",
    ),
}

#: Nodes under ``Machines/<id>/Proposals`` (see :meth:`ScadaServer.show_proposals`).
PROPOSAL_NODES = (
    ("Proposals.OpenJson", "String", "Open proposals, a JSON list (no model documents)"),
    ("Proposals.OpenCount", "UInt32", "Number of open proposals"),
    ("Proposals.NewestId", "String", "Id of the newest proposal (empty: none)"),
    ("Proposals.NewestEffect", "String", "Effect the newest proposal adds"),
    ("Proposals.NewestParamsJson", "String", "Parameters of that effect, a JSON object"),
    ("Proposals.NewestBeforeUm", "Double", "Held-out RMSE before, on the logged data"),
    ("Proposals.NewestAfterUm", "Double", "Held-out RMSE after, on the logged data"),
    ("Proposals.NewestStatus", "String", "proposed, promoted, rejected or superseded"),
    ("Proposals.ModelsVersion", "UInt32", "Version of the promoted set the machine runs"),
    ("Proposals.LastAction", "String", "Outcome of the last PromoteProposal/RollbackModels"),
)


# -- identities and permissions -------------------------------------------------------


@dataclass
class _SessionUser(User):
    """asyncua's session user plus whether this identity may write."""

    may_write: bool = False


_NO_VIEWER = {
    ua.ObjectIds.WriteRequest_Encoding_DefaultBinary,
    ua.ObjectIds.CallRequest_Encoding_DefaultBinary,
}
_OPERATOR_REQUESTS = frozenset(node_id(t) for t in USER_TYPES)
_VIEWER_REQUESTS = frozenset(node_id(t) for t in USER_TYPES if t not in _NO_VIEWER)


class _RoleRuleset(PermissionRuleset):
    """Per request type: operators may read, subscribe and write; others only read."""

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        if not isinstance(user, _SessionUser):  # a session that was never activated
            return False
        allowed = _OPERATOR_REQUESTS if user.may_write else _VIEWER_REQUESTS
        return action_type_id in allowed


class _ClientTrust:
    """Certificate check at CreateSession (asyncua's certificate validator hook).

    It raises for a certificate it refuses, which fails that CreateSession; the
    session remembers the certificate it was admitted with (:func:`_watch_peers`),
    so the user manager can refuse a session whose secure channel was opened with
    any other one (or none). The verdict belongs to the session, not to the
    certificate: under a burst, another session's check of the same certificate
    may be under way while this one is activated.
    """

    def __init__(self, pki_dir: Path, trust_all: bool, rejected_keep: int = 50) -> None:
        self._trusted = pki_dir / TRUSTED_DIR
        self._rejected = pki_dir / REJECTED_DIR
        self._crl = pki_dir / CRL_DIR
        self._trust_all = trust_all
        self._rejected_keep = rejected_keep
        self._warned: set[tuple[str, int, int]] = set()  # unreadable trust files named

    async def __call__(self, cert: x509.Certificate, app: ua.ApplicationDescription) -> None:
        der = cert.public_bytes(Encoding.DER)
        options = CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.URI
        store: TrustStore | None = None
        if not self._trust_all:
            options |= CertificateValidatorOptions.TRUSTED | CertificateValidatorOptions.REVOKED
            # Reloaded at every session: a certificate copied into trusted/ counts at once.
            if any(self._trusted.glob("*.*")):
                store = TolerantTrustStore([self._trusted], [self._crl], self._warned)
                await store.load()
        try:
            if not self._trust_all and store is None:
                raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
            await CertificateValidator(options, store).validate(cert, app)
        except ServiceError as err:
            name = status_code(err.code).name
            subject = _common_name(cert)
            if err.code == ua.StatusCodes.BadCertificateUntrusted:
                path, removed = self._save_rejected(cert, der)
                _logger.warning(
                    "SCADA client %r (%s) refused: certificate not trusted, saved as %s; "
                    "move it to %s to trust it%s",
                    subject,
                    app.ApplicationUri,
                    path,
                    self._trusted,
                    f" ({removed} older rejected certificate(s) removed: {self._rejected} "
                    f"keeps the newest {self._rejected_keep})"
                    if removed
                    else "",
                )
            else:
                _logger.warning("SCADA client %r refused: %s", subject, name)
            raise

    def _save_rejected(self, cert: x509.Certificate, der: bytes) -> tuple[Path, int]:
        """Save the certificate, then keep only the newest ``rejected_keep``; (path, removed)."""
        # The SHA-1 thumbprint is how OPC UA tools name a certificate (an id, not a hash).
        thumbprint = cert.fingerprint(hashes.SHA1()).hex()
        label = re.sub(r"[^A-Za-z0-9_.-]+", "_", _common_name(cert))[:60]
        path = self._rejected / f"{label}_{thumbprint}.der"
        path.write_bytes(der)
        saved = [p for p in self._rejected.glob("*.der") if p.is_file()]
        saved.sort(key=lambda p: (p.stat().st_mtime_ns, p == path))
        excess = [p for p in saved[: max(len(saved) - self._rejected_keep, 0)] if p != path]
        for old in excess:
            old.unlink(missing_ok=True)
        return path, len(excess)


def _common_name(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else "?"


class _QuietTrustStore(logging.Filter):
    """Drops asyncua's traceback for an untrusted certificate: ``_ClientTrust`` logs one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Not trusted certificate used")


_TRUST_STORE_LOGGER = "asyncuagds.validate"  # asyncua.crypto.truststore's logger


class _UserManager(UserManager):
    """asyncua user manager: secure channel + trusted certificate + password → role.

    asyncua does not tell a user manager who is asking; :func:`_watch_peers`
    sets ``peer`` (the remote address) around each ActivateSession, so failed
    logins can be throttled per address as well as per user name, and
    ``admitted_certificate`` (what that session's CreateSession admitted).
    """

    def __init__(
        self,
        users: Sequence[ScadaUser],
        allow_anonymous: bool,
        throttle: LoginThrottle,
    ):
        self._users = {u.username: u for u in users}
        self._allow_anonymous = allow_anonymous
        self.throttle = throttle
        self.peer: str | None = None
        self.admitted_certificate: bytes | None = None  # the judged session's, at CreateSession

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> User | None:
        admitted = self.admitted_certificate
        if certificate is None or admitted is None or bytes(certificate) != admitted:
            # An unsecured channel (no certificate) or one that CreateSession did not admit.
            _logger.warning("SCADA session refused: no admitted client certificate on the channel")
            return None
        if username is None:  # anonymous token (offered only when allow_anonymous)
            if self._allow_anonymous:
                return _SessionUser(role=UserRole.Anonymous, name="anonymous", may_write=False)
            return None
        address = self.peer or "unknown"
        keys: list[Key] = [("address", address), ("user", username)]
        if self.throttle.refuse_locked(keys):
            return None  # the lockout was logged when it started
        user = self._users.get(username)
        expected = (user.password if user is not None else "\0 no such user").encode()
        given = (password or "").encode()
        if user is None or not hmac.compare_digest(given, expected):
            _logger.warning("SCADA login refused for user %r from %s", username, address)
            policy = self.throttle.policy
            for lockout in self.throttle.failed(keys):
                kind, value = lockout.key
                _logger.warning(
                    "SCADA logins %s %s locked for %.0f s after %d failed attempts within "
                    "%.0f s; every login through it is refused until then",
                    "from address" if kind == "address" else "as user",
                    value if kind == "address" else repr(value),
                    lockout.duration_s,
                    lockout.failures,
                    policy.window_s,
                )
            return None
        self.throttle.succeeded(keys)
        return _SessionUser(
            role=UserRole.User, name=user.username, may_write=user.role == "operator"
        )


def _watch_peers(server: Server, manager: _UserManager) -> None:
    """Tell ``manager`` the remote address and the admitted certificate of every
    ActivateSession it judges.

    asyncua names each session by the peer's (host, port) and calls the user
    manager synchronously inside ``InternalSession.activate_session``; wrapping
    that call on every new session lets ``manager.peer`` hold the host meanwhile.
    The session's own CreateSession is wrapped too: the certificate it carried is
    kept only if the check (:class:`_ClientTrust`) let it pass. asyncua keeps a
    session whose CreateSession failed, so a client could still try to activate it.
    """
    iserver = server.iserver
    create_session = iserver.create_session

    def create_watched_session(name: Any, *args: Any, **kwargs: Any) -> Any:
        session = create_session(name, *args, **kwargs)
        create, activate = session.create_session, session.activate_session
        host = str(name[0]) if isinstance(name, tuple) and name else str(name)
        admitted: list[bytes] = []

        async def create_checked(params: ua.CreateSessionParameters, *a: Any, **kw: Any) -> Any:
            admitted.clear()
            result = await create(params, *a, **kw)  # raises if the certificate is refused
            if params.ClientCertificate:
                admitted.append(bytes(params.ClientCertificate))
            return result

        def activate_session(*a: Any, **kw: Any) -> Any:
            manager.peer = host
            manager.admitted_certificate = admitted[0] if admitted else None
            try:
                return activate(*a, **kw)
            finally:
                manager.peer = None
                manager.admitted_certificate = None

        # asyncua has no hook for this: its methods are wrapped in place, on purpose.
        session.create_session = create_checked  # type: ignore[method-assign]
        session.activate_session = activate_session  # type: ignore[method-assign]
        return session

    iserver.create_session = create_watched_session  # type: ignore[method-assign]


# -- the server -----------------------------------------------------------------------


def _now() -> datetime:
    return datetime.now(UTC)


def _source_time(record: CycleRecord) -> ua.DateTime | None:
    """When the cycle measured its values: the wall stamp every output of the cycle carries
    (None for a simulation's machine time counted from 0: the values are stamped now)."""
    stamp_s = record.stamped_s
    return ua_datetime(datetime.fromtimestamp(stamp_s, UTC)) if stamp_s >= 1e9 else None


def _dv(variant: ua.Variant, status: int = ua.StatusCodes.Good) -> ua.DataValue:
    return data_value(variant, status)


def _double(value: float | None, missing: int = ua.StatusCodes.BadNoData) -> ua.DataValue:
    if value is None or not math.isfinite(value):
        return _dv(ua.Variant(math.nan, ua.VariantType.Double), missing)
    return _dv(ua.Variant(float(value), ua.VariantType.Double))


def _string(value: str | None) -> ua.DataValue:
    return _dv(ua.Variant(value or "", ua.VariantType.String))


def _uint32(value: float | int | str) -> ua.DataValue:
    count = min(max(int(value), 0), 2**32 - 1)
    return _dv(ua.Variant(count, ua.VariantType.UInt32))


def _temperature(value: float | None, quality: str | None, reason: str | None) -> ua.DataValue:
    """A temperature with its quality as the StatusCode (Bad values read as null)."""
    if value is None or not math.isfinite(value):
        status = ua.StatusCodes.BadSensorFailure if quality == "bad" else ua.StatusCodes.BadNoData
    elif quality == "good":
        status = ua.StatusCodes.Good
    elif reason is not None and reason.startswith("recovering"):
        status = ua.StatusCodes.Uncertain  # plausible again, not yet trusted
    else:
        status = ua.StatusCodes.BadSensorFailure
    shown = value if value is not None else math.nan
    return _dv(ua.Variant(float(shown), ua.VariantType.Double), status)


#: The nodes of one axis of a multi-axis machine, in ``Axes.<A>``: today's per-axis node
#: names (name, kind, description, in µm), and the axis's macro number.
AXIS_NODES = (
    ("ModelId", "String", "Model in use on this axis (empty: none)", False),
    ("PredictedUm", "Double", "Predicted thermal error rise of this axis", True),
    ("IntervalUm", "Double", "Half-width of the 90 % interval (NaN: unknown)", True),
    ("TrainingSpan", "String", "inside / outside the training span (empty: unknown)", False),
    ("OutsideInputs", "String", "Inputs outside the training span", False),
    ("CompensationUm", "Double", "Compensation of this axis applied by the CNC", True),
    ("LastWriteStatus", "String", "Outcome of this axis's last CNC write", False),
    ("Macro", "UInt32", "Macro variable this axis's compensation is written to", False),
)


def _axis_values(axis: AxisRecord) -> list[tuple[str, ua.DataValue]]:
    """One axis's node values (names relative to ``Axes.<A>``), as :data:`AXIS_NODES`."""
    return [
        ("ModelId", _string(axis.model_id)),
        ("PredictedUm", _double(axis.predicted_um)),
        ("IntervalUm", _double(axis.interval_um)),
        ("TrainingSpan", _string(axis.training_span)),
        ("OutsideInputs", _string(",".join(axis.outside_inputs))),
        ("CompensationUm", _double(axis.applied_um)),
        ("LastWriteStatus", _string(axis.write_status)),
        ("Macro", _uint32(axis.macro)),
    ]


class ScadaServer(ServerLifecycle):
    """The secured OPC UA server SCADA connects to (address space in ``docs/scada.md``).

    ``machines`` lists the machine ids, or maps each id to its sensor names so the
    temperature nodes exist from the start (a sensor first seen in a record gets
    its node then). ``axes`` maps a multi-axis machine's id to its axes in configured
    order, each with its macro number (:func:`gateway.outputs.axes.axis_macros`): their
    ``Axes`` folders exist from the start (an axis first seen in a record gets its folder
    then). ``on_enable(machine, enabled)`` is called for every write to a
    ``CompensationEnabled`` node that an operator makes; if it raises, the write
    fails (BadInternalError) and the node keeps its value.
    """

    def __init__(
        self,
        settings: ScadaSettings,
        machines: Sequence[str] | Mapping[str, Sequence[str]],
        on_enable: Callable[[str, bool], None],
        clock: Callable[[], float] = time.monotonic,
        *,
        on_promote: Callable[[str, str], str] | None = None,
        on_rollback: Callable[[str], str] | None = None,
        axes: Mapping[str, Mapping[str, int | None]] | None = None,
    ) -> None:
        """``clock`` (seconds) times login lockouts; tests pass a manual one.

        ``on_promote(machine, proposal_id)`` and ``on_rollback(machine)`` serve the
        operators' ``PromoteProposal`` and ``RollbackModels`` methods: they return a
        line for ``Proposals.LastAction``; KeyError means an unknown id
        (``BadNotFound``), ValueError a change refused (``BadInvalidState``), the
        reason going to ``LastAction`` and the log. Without them the methods answer
        ``BadNotImplemented``.
        """
        if isinstance(machines, Mapping):
            sensors = {str(m): tuple(s) for m, s in machines.items()}
        else:
            sensors = {str(m): () for m in machines}
        if not sensors:
            raise ValueError("at least one machine is needed")
        if len(sensors) != len(machines):
            raise ValueError(f"machine ids must be unique, got {list(machines)}")
        if any(not m or m == "Machines" for m in sensors):
            raise ValueError(f"invalid machine id in {list(sensors)}")
        self._settings = settings
        self._sensors = sensors
        self._axes = {str(m): dict(a) for m, a in (axes or {}).items() if a}
        if unknown := set(self._axes) - set(sensors):
            raise ValueError(f"axes given for machines not served: {sorted(unknown)}")
        self._axes_parent: dict[str, Node] = {}
        self._on_enable = on_enable
        self._on_promote = on_promote
        self._on_rollback = on_rollback
        self.login_throttle = LoginThrottle(settings.login_throttle, clock)
        self._server: Server | None = None
        self._ns: int | None = None
        self._nodeids: dict[str, ua.NodeId] = {}
        self._temperature_parent: dict[str, Node] = {}
        self._machine_of_switch: dict[ua.NodeId, str] = {}
        # The DataValue publish() is writing right now: the switch's setter sees it
        # synchronously and must not take it for a client's write.
        self._publishing: ua.DataValue | None = None
        self._lock = asyncio.Lock()
        self._tasks: set[asyncio.Task[None]] = set()

    # -- public API -------------------------------------------------------------------

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self._settings.host}:{self._settings.port}/scada"

    @property
    def namespace_index(self) -> int:
        if self._ns is None:
            raise RuntimeError("the namespace index is known only after start()")
        return self._ns

    @property
    def certificate_file(self) -> Path:
        return self._settings.pki_dir / SERVER_CERT

    @staticmethod
    def node_id(machine: str, name: str) -> str:
        """String node id of a machine variable, e.g. ``vmc-1.SpeedRpm``."""
        return f"{machine}.{name}"

    async def start(self) -> None:
        """Create or load the certificate, build the address space, then listen."""
        self._refuse_second_start()
        settings = self._settings
        trust = _ClientTrust(settings.pki_dir, settings.trust_all_clients, settings.rejected_keep)
        await self._ensure_certificate()
        manager = _UserManager(settings.users, settings.allow_anonymous, self.login_throttle)
        server = Server(user_manager=manager)
        _watch_peers(server, manager)
        trust_store_log = logging.getLogger(_TRUST_STORE_LOGGER)
        if not any(isinstance(f, _QuietTrustStore) for f in trust_store_log.filters):
            trust_store_log.addFilter(_QuietTrustStore())
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("Spindle thermal compensation gateway (SCADA)")
        server.application_type = ua.ApplicationType.Server
        await server.set_application_uri(settings.application_uri)
        await server.load_certificate(str(settings.pki_dir / SERVER_CERT))
        await server.load_private_key(str(settings.pki_dir / SERVER_KEY))
        server.set_security_policy(
            [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt],
            permission_ruleset=_RoleRuleset(),  # type: ignore[arg-type]
        )
        tokens: list[type] = [ua.UserNameIdentityToken]
        if settings.allow_anonymous:
            tokens.append(ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        server.allow_remote_admin(False)
        server.set_certificate_validator(trust)
        self._ns = await server.register_namespace(NAMESPACE)
        await self._listen(server, self._build_address_space)
        _logger.info("SCADA OPC UA server on %s", self.endpoint)

    async def stop(self) -> None:
        """Cancel pending publishes, then close connections and the socket (idempotent)."""
        for task in list(self._tasks):
            task.cancel()
        await super().stop()

    async def publish(self, record: CycleRecord, health: Mapping[str, float | int | str]) -> None:
        """Show one cycle's record and the loop's health counters.

        ``health`` keys: the counters of :data:`HEALTH_COUNTERS` and
        ``compensation_enabled`` (the loop's current switch state); see
        :func:`gateway.outputs.health.machine_health`. Missing keys leave their nodes as they are.
        """
        server = self._require_started()
        machine = record.machine
        if machine not in self._sensors:
            raise KeyError(f"machine {machine!r} is not served (known: {list(self._sensors)})")
        async with self._lock:
            for sensor in record.temperatures_C:
                if self.node_id(machine, f"Temperatures.{sensor}") not in self._nodeids:
                    await self._add_temperature(machine, sensor)
            values: list[tuple[str, ua.DataValue]] = [
                (
                    f"Temperatures.{sensor}",
                    _temperature(
                        value, record.quality.get(sensor), record.quality_reasons.get(sensor)
                    ),
                )
                for sensor, value in record.temperatures_C.items()
            ]
            values += [
                ("SpeedRpm", _double(record.speed_rpm, ua.StatusCodes.BadNoCommunication)),
                ("Regime", _string(record.regime)),
                ("ModelId", _string(record.model_id)),
                ("PredictedUm", _double(record.predicted_um)),
                ("IntervalUm", _double(record.interval_um)),
                ("TrainingSpan", _string(record.training_span)),
                ("OutsideInputs", _string(",".join(record.outside_inputs))),
                ("CompensationUm", _double(record.applied_um)),
                ("LastWriteStatus", _string(record.write_status)),
                ("Health.LinkErrors", _uint32(len(record.link_errors))),
            ]
            values += [
                (node, _uint32(health[key]))
                for key, (node, _) in HEALTH_COUNTERS.items()
                if key in health
            ]
            for name, axis in record.axes.items():
                if self.node_id(machine, f"Axes.{name}.Macro") not in self._nodeids:
                    await self._add_axis(machine, name)
                values += [(f"Axes.{name}.{node}", dv) for node, dv in _axis_values(axis)]
            measured = _source_time(record)
            for name, datavalue in values:
                if measured is not None:
                    datavalue.SourceTimestamp = measured
                await server.write_attribute_value(
                    self._nodeids[self.node_id(machine, name)], datavalue
                )
            if "compensation_enabled" in health:
                await self._show_enabled(machine, bool(health["compensation_enabled"]))

    async def show_proposals(self, machine: str, view: Mapping[str, Any]) -> None:
        """Show a machine's proposals: ``view`` holds ``open`` (proposal summaries as
        :meth:`models.online.proposals.Proposal.summary` gives them), ``newest`` (one summary
        or None) and ``models_version`` (int)."""
        server = self._require_started()
        if machine not in self._sensors:
            raise KeyError(f"machine {machine!r} is not served (known: {list(self._sensors)})")
        newest = view.get("newest") or {}
        opened = list(view.get("open") or [])
        values = {
            "Proposals.OpenJson": _string(json.dumps(opened, ensure_ascii=False)),
            "Proposals.OpenCount": _uint32(len(opened)),
            "Proposals.NewestId": _string(newest.get("id")),
            "Proposals.NewestEffect": _string(newest.get("effect")),
            "Proposals.NewestParamsJson": _string(
                json.dumps(newest.get("params") or {}, ensure_ascii=False)
            ),
            "Proposals.NewestBeforeUm": _double(newest.get("before_rmse_um")),
            "Proposals.NewestAfterUm": _double(newest.get("after_rmse_um")),
            "Proposals.NewestStatus": _string(newest.get("status")),
            "Proposals.ModelsVersion": _uint32(int(view.get("models_version") or 0)),
        }
        async with self._lock:
            for name, datavalue in values.items():
                await server.write_attribute_value(
                    self._nodeids[self.node_id(machine, name)], datavalue
                )

    def show_proposals_soon(self, machine: str, view: Mapping[str, Any]) -> asyncio.Task[None]:
        """Schedule :meth:`show_proposals` from synchronous code on the running loop."""
        task = asyncio.get_running_loop().create_task(self.show_proposals(machine, dict(view)))
        self._tasks.add(task)
        task.add_done_callback(self._publish_done)
        return task

    def publish_soon(
        self, record: CycleRecord, health: Mapping[str, float | int | str]
    ) -> asyncio.Task[None]:
        """Schedule :meth:`publish` from synchronous code (a loop sink) on the running loop."""
        task = asyncio.get_running_loop().create_task(self.publish(record, dict(health)))
        self._tasks.add(task)
        task.add_done_callback(self._publish_done)
        return task

    # -- internals --------------------------------------------------------------------

    def _publish_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            _logger.error("SCADA publish failed", exc_info=task.exception())

    async def _ensure_certificate(self) -> None:
        """Create the PKI folders and, on first start (or expiry), the server certificate."""
        pki = self._settings.pki_dir
        pki.mkdir(parents=True, exist_ok=True, mode=0o700)
        for sub in (TRUSTED_DIR, REJECTED_DIR, CRL_DIR):
            (pki / sub).mkdir(exist_ok=True, mode=0o700)
        key_file = pki / SERVER_KEY
        await setup_self_signed_certificate(
            key_file,
            pki / SERVER_CERT,
            self._settings.application_uri,
            socket.gethostname(),
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
            {"organizationName": "spindle-gateway"},
        )
        key_file.chmod(0o600)

    async def _build_address_space(self, server: Server) -> None:
        machines = await self._object(server.nodes.objects, "Machines", "Machines", "CNC machines")
        for machine, sensors in self._sensors.items():
            obj = await self._object(machines, machine, machine, f"Machine {machine}")
            temps = await self._object(
                obj, f"{machine}.Temperatures", "Temperatures", "Spindle temperatures (°C)"
            )
            health = await self._object(
                obj, f"{machine}.Health", "Health", "Gateway health counters"
            )
            self._temperature_parent[machine] = temps
            for sensor in sensors:
                await self._add_temperature(machine, sensor)

            nan = ua.Variant(math.nan, ua.VariantType.Double)
            text = ua.Variant("", ua.VariantType.String)
            zero = ua.Variant(0, ua.VariantType.UInt32)
            for parent, name, initial, description, unit in (
                (obj, "SpeedRpm", nan, "Actual spindle speed", RPM),
                (obj, "Regime", text, "Speed regime (empty: none yet)", None),
                (obj, "ModelId", text, "Model in use (empty: none)", None),
                (obj, "PredictedUm", nan, "Predicted thermal Z error rise", MICROMETRE),
                (
                    obj,
                    "IntervalUm",
                    nan,
                    "Half-width of the 90 % interval (NaN: unknown)",
                    MICROMETRE,
                ),
                (
                    obj,
                    "TrainingSpan",
                    text,
                    "inside / outside the training span (empty: unknown)",
                    None,
                ),
                (obj, "OutsideInputs", text, "Inputs outside the training span", None),
                (obj, "CompensationUm", nan, "Compensation applied by the CNC", MICROMETRE),
                (obj, "LastWriteStatus", text, "Outcome of the last CNC write", None),
                (health, "Health.LinkErrors", zero, "Link errors in the last cycle", None),
                *((health, n, zero, d, None) for n, d in HEALTH_COUNTERS.values()),
            ):
                await self._variable(parent, machine, name, initial, description, unit)

            switch = await self._variable(
                obj,
                machine,
                "CompensationEnabled",
                ua.Variant(False, ua.VariantType.Boolean),
                "Compensation on (true) or off (false); operators may write it",
                None,
            )
            await switch.set_writable()
            self._machine_of_switch[switch.nodeid] = machine
            # asyncua calls the setter after its own checks (access level, Boolean type)
            # in place of storing the value, synchronously within the Write service.
            server.set_attribute_value_setter(switch.nodeid, self._set_enabled)
            await self._build_proposals(obj, machine)
            for axis in self._axes.get(machine, {}):
                await self._add_axis(machine, axis)

    async def _build_proposals(self, obj: Node, machine: str) -> None:
        """The machine's proposal nodes and the operators' two methods."""
        ns = self.namespace_index
        proposals = await self._object(
            obj, f"{machine}.Proposals", "Proposals", "Model proposals and promotions"
        )
        initial = {
            "String": ua.Variant("", ua.VariantType.String),
            "UInt32": ua.Variant(0, ua.VariantType.UInt32),
            "Double": ua.Variant(math.nan, ua.VariantType.Double),
        }
        for name, kind, description in PROPOSAL_NODES:
            unit = MICROMETRE if name.endswith("Um") else None
            await self._variable(proposals, machine, name, initial[kind], description, unit)
        proposal_id = ua.Argument()
        proposal_id.Name = "ProposalId"
        proposal_id.DataType = node_id(ua.ObjectIds.String)
        proposal_id.ValueRank = -1
        proposal_id.Description = ua.LocalizedText("Id of the proposal, e.g. P0001")
        result = ua.Argument()
        result.Name = "Result"
        result.DataType = node_id(ua.ObjectIds.String)
        result.ValueRank = -1
        result.Description = ua.LocalizedText("What changed")
        for name, call, inputs in (
            ("PromoteProposal", self._promote_method, [proposal_id]),
            ("RollbackModels", self._rollback_method, []),
        ):
            await obj.add_method(
                node_id(self.node_id(machine, name), ns),
                ua.QualifiedName(name, ns),
                call,
                inputs,
                [result],
            )

    async def _promote_method(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """``PromoteProposal(ProposalId)``: operators only (the ruleset refuses others)."""
        machine = self._machine_of_object(parent)
        if self._on_promote is None:
            return status_code(ua.StatusCodes.BadNotImplemented)
        if len(args) != 1 or args[0].VariantType != ua.VariantType.String:
            return status_code(ua.StatusCodes.BadInvalidArgument)
        proposal_id = str(args[0].Value or "")
        on_promote = self._on_promote
        return await self._operator_action(
            machine, f"PromoteProposal({proposal_id})", lambda: on_promote(machine, proposal_id)
        )

    async def _rollback_method(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """``RollbackModels()``: operators only (the ruleset refuses others)."""
        machine = self._machine_of_object(parent)
        if self._on_rollback is None:
            return status_code(ua.StatusCodes.BadNotImplemented)
        if args:
            return status_code(ua.StatusCodes.BadTooManyArguments)
        on_rollback = self._on_rollback
        return await self._operator_action(
            machine, "RollbackModels()", lambda: on_rollback(machine)
        )

    async def _operator_action(self, machine: str, what: str, action: Callable[[], str]) -> Any:
        """Run an operator's action; its outcome goes to ``LastAction`` and the log."""
        status = ua.StatusCodes.Good
        try:
            text = action()
        except KeyError as exc:
            status, text = ua.StatusCodes.BadNotFound, str(exc.args[0] if exc.args else exc)
        except ValueError as exc:
            status, text = ua.StatusCodes.BadInvalidState, str(exc)
        except Exception:
            _logger.exception("SCADA %s on %s failed", what, machine)
            status, text = ua.StatusCodes.BadInternalError, "internal error (see the log)"
        line = f"{what}: {text}" if status == ua.StatusCodes.Good else f"{what} refused: {text}"
        (_logger.warning if status == ua.StatusCodes.Good else _logger.error)(
            "SCADA operator on %s: %s", machine, line
        )
        server = self._require_started()
        async with self._lock:
            await server.write_attribute_value(
                self._nodeids[self.node_id(machine, "Proposals.LastAction")], _string(line)
            )
        if status != ua.StatusCodes.Good:
            return status_code(status)
        return [ua.Variant(text, ua.VariantType.String)]

    def _machine_of_object(self, parent: ua.NodeId) -> str:
        text = parent.Identifier if isinstance(parent.Identifier, str) else ""
        if text not in self._sensors:
            raise KeyError(f"{parent} is not a machine")
        return text

    async def _object(self, parent: Node, nodeid: str, browse: str, description: str) -> Node:
        node = await parent.add_object(
            node_id(nodeid, self.namespace_index), ua.QualifiedName(browse, self.namespace_index)
        )
        await node.write_attribute(
            ua.AttributeIds.Description, data_value(ua.LocalizedText(description), stamped=False)
        )
        return node

    async def _variable(
        self,
        parent: Node,
        machine: str,
        name: str,
        initial: ua.Variant,
        description: str,
        unit: ua.EUInformation | None,
    ) -> Node:
        ns = self.namespace_index
        nodeid = self.node_id(machine, name)
        node = await parent.add_variable(
            node_id(nodeid, ns), ua.QualifiedName(name.rsplit(".", 1)[-1], ns), initial
        )
        await node.write_attribute(
            ua.AttributeIds.Description, data_value(ua.LocalizedText(description), stamped=False)
        )
        if unit is not None:
            await node.add_property(
                node_id(f"{nodeid}.EngineeringUnits", ns),
                ua.QualifiedName("EngineeringUnits", 0),
                ua.Variant(unit, ua.VariantType.ExtensionObject),
                datatype=node_id(ua.ObjectIds.EUInformation),
            )
        # No value until the first publish(): SCADA sees "waiting", not a fake zero.
        await node.write_value(_dv(initial, ua.StatusCodes.BadWaitingForInitialData))
        self._nodeids[nodeid] = node.nodeid
        return node

    async def _add_temperature(self, machine: str, sensor: str) -> None:
        await self._variable(
            self._temperature_parent[machine],
            machine,
            f"Temperatures.{sensor}",
            ua.Variant(math.nan, ua.VariantType.Double),
            f"Temperature {sensor}; StatusCode: Good, Uncertain (recovering) or Bad",
            CELSIUS,
        )

    async def _add_axis(self, machine: str, axis: str) -> None:
        """The folder ``Axes.<axis>`` of a multi-axis machine and its variables (and the
        ``Axes`` folder with the first axis)."""
        if machine not in self._axes_parent:
            machine_node = self._require_started().get_node(node_id(machine, self.namespace_index))
            self._axes_parent[machine] = await self._object(
                machine_node, f"{machine}.Axes", "Axes", "Each compensated axis"
            )
        folder = await self._object(
            self._axes_parent[machine], f"{machine}.Axes.{axis}", axis, f"Axis {axis}"
        )
        initial = {
            "String": ua.Variant("", ua.VariantType.String),
            "UInt32": ua.Variant(0, ua.VariantType.UInt32),
            "Double": ua.Variant(math.nan, ua.VariantType.Double),
        }
        for name, kind, description, in_um in AXIS_NODES:
            unit = MICROMETRE if in_um else None
            await self._variable(
                folder, machine, f"Axes.{axis}.{name}", initial[kind], description, unit
            )
        macro = self._axes.get(machine, {}).get(axis)
        if macro is not None:  # known from the configuration before any cycle
            await self._require_started().write_attribute_value(
                self._nodeids[self.node_id(machine, f"Axes.{axis}.Macro")], _uint32(macro)
            )

    async def _show_enabled(self, machine: str, enabled: bool) -> None:
        server = self._require_started()
        nodeid = self._nodeids[self.node_id(machine, "CompensationEnabled")]
        current = server.read_attribute_value(nodeid)
        if (
            current.StatusCode is not None
            and current.StatusCode.is_good()
            and current.Value is not None
            and current.Value.Value == enabled
        ):
            return  # unchanged: no needless data-change notification
        datavalue = _dv(ua.Variant(enabled, ua.VariantType.Boolean))
        self._publishing = datavalue
        try:
            await server.write_attribute_value(nodeid, datavalue)
        finally:
            self._publishing = None

    def _set_enabled(self, node: NodeData, attr: ua.AttributeIds, value: ua.DataValue) -> None:
        """Store the switch's new value; an operator's write goes to ``on_enable`` first.

        Only operators reach this (the ruleset refuses other users' Write requests).
        Raising a ``UaStatusCodeError`` makes asyncua answer the Write request with
        that status, and the node keeps its old value.
        """
        attval = node.attributes[attr]
        if value is self._publishing:
            attval.value = value
            return
        variant = value.Value
        if variant is None or variant.VariantType != ua.VariantType.Boolean:
            raise ua.uaerrors.BadTypeMismatch()
        machine = self._machine_of_switch[node.nodeid]
        enabled = bool(variant.Value)
        try:
            self._on_enable(machine, enabled)
        except Exception as err:
            _logger.exception("on_enable(%r, %r) failed", machine, enabled)
            raise ua.uaerrors.BadInternalError() from err
        _logger.info("SCADA operator set %s compensation %s", machine, "on" if enabled else "off")
        attval.value = _dv(ua.Variant(enabled, ua.VariantType.Boolean))
