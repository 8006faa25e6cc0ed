"""The gateway's configuration: one YAML file, several machines, checked once at start.

Every problem is refused before anything runs, with the file, the line and the
key path (``config.yaml:23: machines[0].compensation.clamp_um: …``). Secrets
never live in the file: a password is named by ``password_env`` (an environment
variable) or ``password_file`` (a file readable by the gateway only).

The ``simulator`` section (served by ``python -m gateway simulate``) is checked
by :mod:`simulator.serve`; this module checks everything else.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from gateway.compensation import CompensationLimits
from gateway.quality import QualityLimits
from models.regime_rules import RegimeRules, SpeedBand


class ConfigError(ValueError):
    """A configuration problem, located: file, line, key path."""


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DeviceSection(Strict):
    device_id: int = Field(ge=1, le=247)
    channels: list[str | None] = Field(min_length=1, max_length=8)


class RtuSection(Strict):
    port: str
    baudrate: int = 19200
    parity: Literal["N", "E", "O"] = "N"


class TcpSection(Strict):
    host: str
    port: int = Field(ge=1, le=65535)


class BusSection(Strict):
    name: str
    rtu: RtuSection | None = None
    tcp: TcpSection | None = None
    timeout_s: float = Field(default=0.3, gt=0)
    devices: list[DeviceSection] = Field(min_length=1)

    @model_validator(mode="after")
    def _one_transport(self) -> BusSection:
        if (self.rtu is None) == (self.tcp is None):
            raise ValueError("give exactly one of 'rtu' or 'tcp'")
        return self


class SensorSection(Strict):
    location: str = ""
    min_C: float = -20.0
    max_C: float = 120.0
    max_rate_C_per_s: float = Field(default=0.5, gt=0)
    stuck_s: float = Field(default=900.0, gt=0)
    stale_s: float = Field(default=10.0, gt=0)


class Credentials(Strict):
    username: str | None = None
    password_env: str | None = None
    password_file: Path | None = None

    def password(self) -> str | None:
        """The secret, read from the environment or the file named in the config."""
        if self.password_env:
            value = os.environ.get(self.password_env)
            if value is None:
                raise ConfigError(
                    f"environment variable {self.password_env} (password_env) is not set"
                )
            return value
        if self.password_file:
            try:
                return self.password_file.read_text(encoding="utf-8").strip()
            except OSError as exc:
                raise ConfigError(f"password_file {self.password_file}: {exc.strerror}") from None
        return None


class OpcUaCncSection(Credentials):
    endpoint: str
    namespace: str = "urn:spindle-gateway:simulated-cnc"
    speed_node: str = "Spindle.ActualSpeed"
    commanded_node: str = "Spindle.CommandedSpeed"
    run_mode_node: str | None = "Cnc.RunMode"
    macro_node: str = "Macro.{n}"
    timeout_s: float = Field(default=2.0, gt=0)

    @field_validator("endpoint")
    @classmethod
    def _opc_tcp(cls, value: str) -> str:
        if not value.startswith("opc.tcp://"):
            raise ValueError(f"expected an opc.tcp:// endpoint, got '{value}'")
        return value

    @field_validator("macro_node")
    @classmethod
    def _has_number(cls, value: str) -> str:
        if "{n}" not in value:
            raise ValueError("must contain {n}, the macro variable number (e.g. 'Macro.{n}')")
        return value


class ModbusCncSection(Strict):
    host: str
    port: int = Field(ge=1, le=65535)
    device_id: int = Field(default=1, ge=1, le=247)
    speed_register: int = 0
    commanded_register: int = 2
    run_mode_register: int = 4
    macro_base_register: int = 1000
    timeout_s: float = Field(default=1.0, gt=0)


class CncSection(Strict):
    opcua: OpcUaCncSection | None = None
    modbus: ModbusCncSection | None = None

    @model_validator(mode="after")
    def _one_link(self) -> CncSection:
        if (self.opcua is None) == (self.modbus is None):
            raise ValueError("give exactly one of 'opcua' or 'modbus'")
        return self


class CompensationSection(Strict):
    enabled: bool = True
    macro: int = Field(default=500, ge=500, le=999)
    unit: Literal["mm", "um"] = "mm"
    sign: Literal[1, -1] = 1
    clamp_um: float = Field(default=50.0, gt=0)
    slew_um_per_min: float = Field(default=20.0, gt=0)
    deadband_um: float = Field(default=0.5, ge=0)
    decimals: int = Field(default=4, ge=0, le=8)
    handshake_macro: int | None = Field(default=None, ge=500, le=999)
    probe_macro: int | None = Field(default=None, ge=500, le=999)  # measured error, µm

    def limits(self) -> CompensationLimits:
        return CompensationLimits(
            clamp_um=self.clamp_um,
            slew_um_per_min=self.slew_um_per_min,
            deadband_um=self.deadband_um,
            unit=self.unit,
            sign=self.sign,
            decimals=self.decimals,
        )


class BandSection(Strict):
    name: str
    min_rpm: float = Field(ge=0)
    max_rpm: float = Field(gt=0)


class RegimeSection(Strict):
    window_s: float = Field(default=1800.0, gt=0)
    constant_tolerance_rpm: float = Field(default=150.0, ge=0)
    min_dwell_s: float = Field(default=600.0, ge=0)
    bands: list[BandSection] = Field(default_factory=list)
    models: dict[str, str] = Field(default_factory=dict)
    fallback_model: str | None = None

    def rules(self) -> RegimeRules:
        return RegimeRules(
            window_s=self.window_s,
            constant_tolerance_rpm=self.constant_tolerance_rpm,
            min_dwell_s=self.min_dwell_s,
            bands=tuple(SpeedBand(b.name, b.min_rpm, b.max_rpm) for b in self.bands),
            models=dict(self.models),
            fallback_model=self.fallback_model,
        )


class ReferenceSection(Strict):
    """Temperature reference of the running machine (the cold state the models start from).

    ``first-reading``: each sensor's first good reading after the gateway starts
    with no saved state (start the gateway with the machine cold); kept in
    ``state_dir`` so a restart mid-shift keeps the cold reference.
    ``fixed``: the values given here, °C.
    """

    mode: Literal["first-reading", "fixed"] = "first-reading"
    values_C: dict[str, float] = Field(default_factory=dict)


class ModelsSection(Strict):
    store: Path
    reference: ReferenceSection = ReferenceSection()
    regimes: RegimeSection = RegimeSection()


class MachineSection(Strict):
    id: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    cycle_s: float = Field(default=1.0, gt=0)
    transmitters: list[BusSection] = Field(min_length=1)
    sensors: dict[str, SensorSection] = Field(default_factory=dict)
    cnc: CncSection
    compensation: CompensationSection = CompensationSection()
    models: ModelsSection

    @model_validator(mode="after")
    def _sensor_names(self) -> MachineSection:
        names = [c for bus in self.transmitters for d in bus.devices for c in d.channels if c]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"sensor(s) {duplicates} appear on more than one channel")
        unknown = sorted(set(self.sensors) - set(names))
        if unknown:
            raise ValueError(f"sensors {unknown} are configured but on no transmitter channel")
        comp = self.compensation
        used = [m for m in (comp.handshake_macro, comp.probe_macro) if m is not None]
        if comp.macro in used:
            raise ValueError(f"macro #{comp.macro} is used twice in compensation")
        return self

    @property
    def sensor_names(self) -> list[str]:
        return [c for bus in self.transmitters for d in bus.devices for c in d.channels if c]

    def quality_limits(self) -> dict[str, QualityLimits]:
        limits = {}
        for name in self.sensor_names:
            s = self.sensors.get(name, SensorSection())
            limits[name] = QualityLimits(
                min_C=s.min_C,
                max_C=s.max_C,
                max_rate_C_per_s=s.max_rate_C_per_s,
                stuck_s=s.stuck_s,
                stale_s=s.stale_s,
            )
        return limits


def from_environment(variable: str, key: str) -> str:
    """The value of ``variable``, named in the config by ``key`` (e.g. ``url_env``)."""
    value = os.environ.get(variable)
    if value is None or not value.strip():
        raise ConfigError(f"environment variable {variable} ({key}) is not set")
    return value.strip()


class InfluxSection(Strict):
    """An InfluxDB 2.x/3.x (or 1.8 with the v2 API) to log to; the token never in the file.

    Each of ``url``, ``org`` and ``bucket`` is given either literally or as the name
    of an environment variable (``url_env``, ``org_env``, ``bucket_env``), as a
    container passes them; the token only ever by ``token_env`` or ``token_file``.
    """

    url: str | None = None
    url_env: str | None = None
    org: str | None = None
    org_env: str | None = None
    bucket: str | None = None
    bucket_env: str | None = None
    token_env: str | None = None
    token_file: Path | None = None
    timeout_s: float = Field(default=10.0, gt=0)

    @model_validator(mode="after")
    def _literal_or_environment(self) -> InfluxSection:
        for key, required in (("url", True), ("org", False), ("bucket", True)):
            literal, variable = getattr(self, key), getattr(self, f"{key}_env")
            if literal is not None and variable is not None:
                raise ValueError(f"give '{key}' or '{key}_env', not both")
            if required and literal is None and variable is None:
                raise ValueError(f"give '{key}' or '{key}_env' (an environment variable)")
        return self

    def _setting(self, key: str, default: str | None = None) -> str:
        variable = getattr(self, f"{key}_env")
        if variable is not None:
            return from_environment(variable, f"{key}_env")
        literal = getattr(self, key)
        return default if literal is None else literal

    def url_value(self) -> str:
        return self._setting("url")

    def org_value(self) -> str:
        return self._setting("org", "-")  # InfluxDB 1.8 takes any org

    def bucket_value(self) -> str:
        return self._setting("bucket")

    def token(self) -> str:
        if self.token_env:
            value = os.environ.get(self.token_env)
            if value is None:
                raise ConfigError(f"environment variable {self.token_env} (token_env) is not set")
            return value
        if self.token_file:
            try:
                return self.token_file.read_text(encoding="utf-8").strip()
            except OSError as exc:
                raise ConfigError(f"token_file {self.token_file}: {exc.strerror}") from None
        return "-"  # InfluxDB 1.8 without authentication accepts any token


class LoggingSection(Strict):
    """Where every cycle is logged.

    With ``influxdb``: points go to a disk buffer first (``buffer_path``, at most
    ``buffer_max_points``; when full the oldest are dropped, counted and reported)
    and are forwarded in order; a database outage or a gateway restart loses
    nothing. Without it: points go to the embedded ``local_store`` (SQLite).
    """

    influxdb: InfluxSection | None = None
    local_store: Path = Path(".cache/data/points.sqlite")
    buffer_path: Path = Path(".cache/data/buffer.sqlite")
    buffer_max_points: int = Field(default=2_000_000, ge=1000)
    # Retention (deploy/README.md, "Disk use"): points older than *_retention_days go,
    # and the oldest go while a file holds more than *_max_mb (10⁶ bytes), checked every
    # retention_interval_s. Defaults: a 16 GB edge disk; they hold days, not a year, of
    # ten machines at 1 Hz (~300 bytes a point in the store, ~150 in the buffer).
    local_store_retention_days: float = Field(default=365.0, gt=0)
    local_store_max_mb: float = Field(default=8000.0, ge=1)
    buffer_retention_days: float = Field(default=30.0, gt=0)
    buffer_max_mb: float = Field(default=1000.0, ge=1)
    retention_interval_s: float = Field(default=60.0, gt=0)


class ScadaUserSection(Credentials):
    username: str  # type: ignore[assignment]
    role: Literal["operator", "viewer"] = "viewer"


class ScadaSection(Strict):
    """The gateway's own OPC UA server for SCADA (Basic256Sha256 SignAndEncrypt only).

    ``host`` 0.0.0.0 serves every interface (a container); client certificates
    must be copied into ``<pki_dir>/trusted`` (see gateway/SCADA.md).
    """

    host: str = "127.0.0.1"
    port: int = Field(default=4841, ge=1, le=65535)
    pki_dir: Path = Path(".cache/state/pki")
    allow_anonymous: bool = False
    users: list[ScadaUserSection] = Field(default_factory=list)


class GatewayConfig(Strict):
    machines: list[MachineSection] = Field(min_length=1)
    state_dir: Path = Path(".cache/state")
    logging: LoggingSection = LoggingSection()
    scada: ScadaSection | None = None
    simulator: dict[str, Any] | None = None  # checked by simulator.serve

    @model_validator(mode="after")
    def _unique_ids(self) -> GatewayConfig:
        ids = [m.id for m in self.machines]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"machine id(s) {duplicates} used twice")
        return self


def key_lines(text: str) -> dict[tuple[str | int, ...], int]:
    """1-based line of every key path in a YAML document (mappings and lists)."""
    lines: dict[tuple[str | int, ...], int] = {}

    def walk(node: yaml.Node, path: tuple[str | int, ...]) -> None:
        lines.setdefault(path, node.start_mark.line + 1)
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                child = (*path, key.value)
                lines[child] = key.start_mark.line + 1
                walk(value, child)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                walk(item, (*path, i))

    root = yaml.compose(text)
    if root is not None:
        walk(root, ())
    return lines


def format_path(loc: tuple[str | int, ...]) -> str:
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"


def locate(path: Path, lines: dict[tuple[str | int, ...], int], loc: tuple[str | int, ...]) -> str:
    """'file:line: key.path' for the deepest part of ``loc`` the file has."""
    for depth in range(len(loc), -1, -1):
        if loc[:depth] in lines:
            return f"{path}:{lines[loc[:depth]]}: {format_path(loc)}"
    return f"{path}: {format_path(loc)}"


def load_config(path: str | Path) -> GatewayConfig:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file") from None
    try:
        raw = yaml.safe_load(text)
        lines = key_lines(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        raise ConfigError(f"{where}: not valid YAML ({getattr(exc, 'problem', exc)})") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}:1: a mapping with a 'machines' list was expected")
    try:
        return GatewayConfig.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = tuple(
            p for p in first["loc"] if not (isinstance(p, str) and p.startswith("function-"))
        )
        message = first["msg"].removeprefix("Value error, ")
        if first["type"] == "missing":
            message = "required key is missing"
        elif first["type"] == "extra_forbidden":
            message = "unknown key (not part of the configuration)"
        raise ConfigError(f"{locate(path, lines, loc)}: {message}") from None
