"""The gateway's configuration: one YAML file, several machines, checked once at start.

Every problem is refused before anything runs, with the file, the line and the
key path (``config.yaml:23: machines[0].compensation.clamp_um: …``). Secrets
never live in the file: a password is named by ``password_env`` (an environment
variable) or ``password_file`` (a file readable by the gateway only).

The file is read by :mod:`drivers.yaml_loader` (duplicate keys, alias bombs,
non-finite numbers, encodings: refused with the line). Buses, ports, devices
and their register maps are the shared models of :mod:`drivers.schema`; a
device's ``map`` (a shipped map's name, a file relative to this one, or inline)
is checked with it, and a problem inside a map file names that file's line. The
``simulator`` section (served by ``python -m gateway simulate``) follows the
schema of :mod:`simulator.serve`, checked here by the same code, with line numbers.

What the CNC cannot hold or a machine tool should never do is refused too:
a clamp beyond :data:`MAX_CLAMP_UM` or beyond the ±9999 units a macro variable
holds, a slew beyond :data:`MAX_SLEW_UM_PER_MIN`, a deadband at or above the
clamp, one macro used for two purposes or written by two machines, a sensor
that would go stale after one missed read (``stale_s < cycle_s``). With
``check_host`` (``check-config`` and ``run``), what depends on the host is
checked too: secrets readable, ``state_dir`` and the stores writable.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal
from urllib.parse import urlsplit

from pydantic import Field, PrivateAttr, ValidationError, field_validator, model_validator

from drivers.schema import (
    Bus,
    Device,
    RegisterMap,
    RtuPort,
    Strict,
    TcpEndpoint,
    Workarounds,
    check_cnc_map,
    cnc_map,
    map_from_source,
)
from drivers.yaml_loader import (
    KeyPathError,
    Loc,
    YamlDocument,
    YamlError,
    first_problem,
    format_path,
    load_yaml,
)
from drivers.yaml_loader import validate as validate_section
from gateway.limits import CompensationLimits, LoginLimits, QualityLimits
from gateway.process.event_loop import DEFAULT as DEFAULT_EVENT_LOOP
from gateway.process.event_loop import EventLoopName
from models.fit.conditioning import DEFAULT_MAX_BIAS_ERROR_UM, DEFAULT_SENSOR_ACCURACY_C
from models.online.correction import CorrectionParams
from models.online.regime_rules import RegimeRules, SpeedBand
from models.online.residual_monitor import MonitorParams

# The map of the ``*_register`` keys is checked field by field (about 50 ms); a plant of
# 1000 machines has a handful of distinct ones. A refused map raises, and is not kept.
_cnc_map_once = functools.lru_cache(maxsize=256)(cnc_map)

if TYPE_CHECKING:  # the plausibility module brings the whole model stack (scipy): not at load
    from drivers.cnc_opcua import OpcUaSecurity
    from gateway.limits import PlausibilityLimits

MAX_CLAMP_UM = 1000.0
"""Largest clamp: thermal growth of a spindle is tens of µm; a bigger clamp is a typo."""
MACRO_MAX_UNITS = 9999
"""Largest magnitude a FANUC macro variable takes as written, in its own unit (mm or µm)."""
MAX_SLEW_UM_PER_MIN = 6000.0
"""Fastest slew: far above any thermal drift (µm per minute); beyond it the limit is no limit."""


class ConfigError(ValueError):
    """A configuration problem, located: file, line, key path."""


def _located(exc: ValueError, prefix: str) -> KeyPathError:
    """A runtime object's refusal (``Prefix.field must …``) blamed on the key of that field."""
    match = re.match(rf"{prefix}\.(\w+):? (?:\((.*?)\) )?(.*)", str(exc), flags=re.DOTALL)
    if match is None:
        return KeyPathError((), str(exc))
    key, value, message = match.groups()
    return KeyPathError((key,), f"{value} {message}" if value else message)


def _host_port(value: str) -> tuple[str, int | None]:
    """Host and port of a URL; a port outside 1…65535 is refused."""
    parts = urlsplit(value)
    try:
        port = parts.port
    except ValueError:
        port = -1
    if port is not None and not 1 <= port <= 65535:
        raise ValueError(f"port out of range in '{value}' (1…65535 expected)")
    if not parts.hostname:
        raise ValueError(f"no host in '{value}'")
    return parts.hostname.lower(), port


# Buses, ports and devices are the shared schema of drivers.schema (the simulator uses it too).
DeviceSection = Device
RtuSection = RtuPort
TcpSection = TcpEndpoint
BusSection = Bus


class SensorSection(Strict):
    location: str = ""
    min_C: float = -20.0
    max_C: float = 120.0
    max_rate_C_per_s: float = Field(default=0.5, gt=0)
    stuck_s: float = Field(default=900.0, gt=0)
    stale_s: float = Field(default=10.0, gt=0)

    @model_validator(mode="after")
    def _range(self) -> SensorSection:
        if self.min_C >= self.max_C:
            key = "min_C" if "min_C" in self.model_fields_set else "max_C"
            raise KeyPathError(
                (key,), f"min_C ({self.min_C:g}) must be below max_C ({self.max_C:g}) °C"
            )
        try:
            QualityLimits(
                min_C=self.min_C,
                max_C=self.max_C,
                max_rate_C_per_s=self.max_rate_C_per_s,
                stuck_s=self.stuck_s,
                stale_s=self.stale_s,
            )
        except ValueError as exc:
            raise _located(exc, "QualityLimits") from None
        return self


class QualitySection(Strict):
    """Plausibility of the sensors and of the prediction (see gateway/live/plausibility.py).

    - ``plausibility_sigma``: a sensor further than this many held-out σ from what
      the other sensors say is held BAD. 5: on unseen simulated programmes (four
      programmes × two seeds, 30 s samples, 9 sensors) the largest |z| of a sound
      sensor was 3.9.
    - ``plausibility_min_sigma_C`` (°C): floor of that σ; 0.1 °C is one register
      step, and what a fast bearing sensor leads the others by through a speed step.
    - ``plausibility_recover_s`` (s): a held sensor must agree for this long before
      it is trusted again; 900 s is 30 cycles at 30 s, far beyond a flicker.
    - ``max_prediction_rate_um_per_s`` (µm/s): fastest believable change of the
      predicted error; 0.1 µm/s = 6 µm/min, seven times the simulated spindle's
      fastest growth from cold (0.8 µm/min).
    - ``prediction_noise_um`` (µm): change allowed on top of that rate (noise
      times the model's coefficients, register steps).
    """

    plausibility_sigma: float = Field(default=5.0, gt=0, allow_inf_nan=False)
    plausibility_min_sigma_C: float = Field(default=0.1, gt=0, allow_inf_nan=False)
    plausibility_recover_s: float = Field(default=900.0, ge=0, allow_inf_nan=False)
    max_prediction_rate_um_per_s: float = Field(default=0.1, gt=0, allow_inf_nan=False)
    prediction_noise_um: float = Field(default=1.0, ge=0, allow_inf_nan=False)

    def limits(self) -> PlausibilityLimits:
        from gateway.limits import PlausibilityLimits

        return PlausibilityLimits(
            sigma=self.plausibility_sigma,
            min_sigma_C=self.plausibility_min_sigma_C,
            recover_s=self.plausibility_recover_s,
            max_prediction_rate_um_per_s=self.max_prediction_rate_um_per_s,
            prediction_noise_um=self.prediction_noise_um,
        )


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

    @model_validator(mode="after")
    def _one_secret(self) -> Credentials:
        if self.password_env and self.password_file:
            raise KeyPathError(("password_file",), "give password_env or password_file, not both")
        return self


class OpcUaSecuritySection(Strict):
    """A signed (and encrypted) channel to a CNC that requires one.

    ``certificate`` / ``private_key``: the gateway's own; made on the first connect
    when neither exists (copy ``certificate`` into the CNC's trusted list once).
    ``server_certificate``: the CNC's certificate to pin; without it the gateway takes
    the one the CNC's endpoint list presents.
    """

    policy: Literal["Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss"] = (
        "Basic256Sha256"
    )
    mode: Literal["Sign", "SignAndEncrypt"] = "SignAndEncrypt"
    certificate: Path
    private_key: Path
    server_certificate: Path | None = None

    def settings(self) -> OpcUaSecurity:
        from drivers.cnc_opcua import OpcUaSecurity  # asyncua only where the link is built

        return OpcUaSecurity(
            self.certificate,
            self.private_key,
            self.policy,
            self.mode,
            self.server_certificate,
        )


class OpcUaCncSection(Credentials):
    endpoint: str
    namespace: str = "urn:spindle-gateway:simulated-cnc"
    speed_node: str = "Spindle.ActualSpeed"
    commanded_node: str = "Spindle.CommandedSpeed"
    run_mode_node: str | None = "Cnc.RunMode"
    macro_node: str = "Macro.{n}"
    timeout_s: float = Field(default=2.0, gt=0)
    security: OpcUaSecuritySection | None = None

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

    @field_validator("endpoint")
    @classmethod
    def _endpoint_address(cls, value: str) -> str:
        _host_port(value)
        return value


class ModbusCncSection(TcpEndpoint):
    """The CNC over Modbus TCP: its registers as a map (``map``) or by the ``*_register`` keys.

    Without ``map`` the keys give the addresses of the simulated CNC's layout
    (``drivers/maps/sim_cnc.yaml``: float32, big byte and word order); with it,
    the map says everything and the keys must be left out.
    """

    device_id: int = Field(default=1, ge=1, le=247)
    speed_register: int = Field(default=0, ge=0, le=65534)
    commanded_register: int = Field(default=2, ge=0, le=65534)
    run_mode_register: int = Field(default=4, ge=0, le=65535)
    macro_base_register: int = Field(default=1000, ge=0, le=65535)
    timeout_s: float = Field(default=1.0, gt=0)
    map: RegisterMap | None = None
    workarounds: Workarounds | None = None

    _load_map = field_validator("map", mode="before")(map_from_source)

    @model_validator(mode="after")
    def _map_or_registers(self) -> ModbusCncSection:
        keys = ("speed_register", "commanded_register", "run_mode_register")
        if self.map is None:
            try:
                self.register_map()
            except ValidationError as exc:  # e.g. two registers overlap
                loc, message = first_problem(exc)
                index = loc[1] if len(loc) > 1 and loc[0] == "fields" else None
                key = keys[index] if isinstance(index, int) else "macro_base_register"
                raise KeyPathError((key,), message) from None
            return self
        given = [k for k in (*keys, "macro_base_register") if k in self.model_fields_set]
        if given:
            raise KeyPathError((given[0],), "give 'map' or the *_register keys, not both")
        check_cnc_map(self.map)
        return self

    def register_map(self) -> RegisterMap:
        """The CNC's registers: the ``map``, or the one the ``*_register`` keys describe."""
        if self.map is not None:
            return self.map
        return _cnc_map_once(
            self.speed_register,
            self.commanded_register,
            self.run_mode_register,
            self.macro_base_register,
        )


class CncSection(Strict):
    opcua: OpcUaCncSection | None = None
    modbus: ModbusCncSection | None = None

    @model_validator(mode="after")
    def _one_link(self) -> CncSection:
        if (self.opcua is None) == (self.modbus is None):
            raise ValueError("give exactly one of 'opcua' or 'modbus'")
        return self


class WhenUncertainSection(Strict):
    """What to do when the prediction is unsure (:mod:`gateway.live.uncertainty_gate`):
    above ``above_um`` of interval half-width, hold the compensation where it is, or
    scale the prediction by ``scale``; either way the change goes through the clamp and
    the slew limit like every other."""

    above_um: float = Field(gt=0, allow_inf_nan=False)
    action: Literal["hold", "scale"] = "hold"
    scale: float = Field(default=0.5, ge=0, le=1)

    @model_validator(mode="after")
    def _scale_with_scale(self) -> WhenUncertainSection:
        if self.action == "hold" and "scale" in self.model_fields_set:
            raise KeyPathError(
                ("scale",), "applies to action 'scale' only; with 'hold' leave it out"
            )
        return self


#: The keys of one axis's write, kept per axis under ``compensation.axes``.
AXIS_WRITE_KEYS = (
    "macro",
    "unit",
    "sign",
    "clamp_um",
    "slew_um_per_min",
    "deadband_um",
    "decimals",
    "hold_on_loss_s",
    "fallback_ramp_um_per_min",
    "when_uncertain",
)
#: Axis names: one upper-case letter of the machine's axes.
AXIS_NAMES = "XYZUVWABC"
#: The axis the single-axis form (``compensation.macro``) compensates.
SINGLE_AXIS = "Z"


class AxisWrite(Strict):
    """How one axis's compensation is written: its macro, unit, limits and safe fallbacks."""

    macro: int = Field(default=500, ge=500, le=999)
    unit: Literal["mm", "um"] = "mm"
    sign: Literal[1, -1] = 1
    clamp_um: float = Field(default=50.0, gt=0)
    slew_um_per_min: float = Field(default=20.0, gt=0)
    deadband_um: float = Field(default=0.5, ge=0)
    decimals: int = Field(default=4, ge=0, le=8)
    # No prediction: hold the value this long after the last prediction, then ramp to 0.
    hold_on_loss_s: float = Field(default=60.0, ge=0, allow_inf_nan=False)
    fallback_ramp_um_per_min: float | None = Field(default=None, gt=0, allow_inf_nan=False)
    # Above this interval half-width, hold or scale the compensation (off: None).
    when_uncertain: WhenUncertainSection | None = None

    def limits(self) -> CompensationLimits:
        return CompensationLimits(
            clamp_um=self.clamp_um,
            slew_um_per_min=self.slew_um_per_min,
            deadband_um=self.deadband_um,
            unit=self.unit,
            sign=self.sign,
            decimals=self.decimals,
            fallback_ramp_um_per_min=self.fallback_ramp_um_per_min,
            hold_on_loss_s=self.hold_on_loss_s,
        )

    @model_validator(mode="after")
    def _safe(self) -> AxisWrite:
        """Refuse what the CNC cannot hold and limits that would not limit."""
        um_per_unit = 1000.0 if self.unit == "mm" else 1.0
        if self.clamp_um / um_per_unit > MACRO_MAX_UNITS:
            raise KeyPathError(
                ("clamp_um",),
                f"{self.clamp_um:.10g} µm is {self.clamp_um / um_per_unit:.10g} {self.unit}; "
                f"the CNC's macro #{self.macro} holds at most ±{MACRO_MAX_UNITS} {self.unit}",
            )
        if self.clamp_um > MAX_CLAMP_UM:
            raise KeyPathError(
                ("clamp_um",),
                f"{self.clamp_um:.10g} µm is more than any thermal compensation needs "
                f"(at most {MAX_CLAMP_UM:g} µm)",
            )
        if self.slew_um_per_min > MAX_SLEW_UM_PER_MIN:
            raise KeyPathError(
                ("slew_um_per_min",),
                f"{self.slew_um_per_min:.10g} µm/min would not limit anything "
                f"(at most {MAX_SLEW_UM_PER_MIN:g} µm/min)",
            )
        if self.deadband_um >= self.clamp_um:
            raise KeyPathError(
                ("deadband_um",),
                f"{self.deadband_um:.10g} µm is not below clamp_um ({self.clamp_um:.10g} µm): "
                "nothing would ever be written",
            )
        try:
            self.limits()
        except ValueError as exc:
            raise _located(exc, "CompensationLimits") from None
        return self


class AxisSection(AxisWrite):
    """One axis of ``compensation.axes``: its write, and the models that predict its error.

    ``target`` (optional) is the error column every model of the axis predicts;
    ``models`` maps a regime to this axis's model id, as ``models.regimes.models`` does
    for the single-axis form; the regime itself is selected once for every axis.
    """

    macro: int = Field(ge=500, le=999)
    target: str | None = Field(default=None, min_length=1)
    models: dict[str, str] = Field(default_factory=dict)
    fallback_model: str | None = None

    def named_models(self) -> dict[str, str]:
        """The model ids this axis names, by the key naming them (``models.<regime>``)."""
        named = {f"models.{regime}": model_id for regime, model_id in self.models.items()}
        if self.fallback_model is not None:
            named["fallback_model"] = self.fallback_model
        return named


class CompensationSection(AxisWrite):
    """What the gateway writes to the CNC. The single-axis form gives one axis's keys
    here (``macro``, ``unit``, ``clamp_um`` …, the Z axis, its models those of
    ``models.regimes``). A machine that compensates several axes gives them under
    ``axes`` instead, each with its own macro, limits and models (the per-axis keys are
    then refused here); ``enabled``, ``handshake_macro``, ``alive_macro``,
    ``probe_macro`` and ``on_disable`` stay machine-wide: one handshake bump per cycle
    covers every axis's write, and the probe, the online correction and the residual
    monitor work on the first axis."""

    enabled: bool = True
    handshake_macro: int | None = Field(default=None, ge=500, le=999)
    probe_macro: int | None = Field(default=None, ge=500, le=999)  # measured error, µm
    # Sign of life for the CNC: a count 1…9999 written every cycle the CNC is reached.
    alive_macro: int | None = Field(default=None, ge=500, le=999)
    # Switched off (here or from SCADA): ramp #macro to 0 at the slew limit, or hold it.
    on_disable: Literal["ramp", "hold"] = "ramp"
    #: Several axes, each with its own macro and models (None: the single-axis form, one
    #: axis named Z written to ``macro``). The first axis is the primary one.
    axes: dict[str, AxisSection] | None = (
        None  # axis name (X, Y, Z …) → its section; in write order
    )

    @model_validator(mode="after")
    def _axes(self) -> CompensationSection:
        """With ``axes``, every per-axis key lives in its axis; the section's own
        per-axis fields then read the first axis's (what a single-axis reader sees)."""
        if self.axes is None:
            return self
        given = sorted(set(AXIS_WRITE_KEYS) & self.model_fields_set, key=AXIS_WRITE_KEYS.index)
        if given:
            raise KeyPathError(
                (given[0],),
                "is a per-axis key: with 'axes' give it in each axis (compensation.axes.<A>)",
            )
        if not self.axes:
            raise KeyPathError(("axes",), "names no axis; give at least one, or leave 'axes' out")
        macros: dict[int, str] = {}
        for name, axis in self.axes.items():
            if len(name) != 1 or name not in AXIS_NAMES:
                raise KeyPathError(
                    ("axes", name), f"axis name: one of {', '.join(AXIS_NAMES)} expected"
                )
            if axis.macro in macros:
                raise KeyPathError(
                    ("axes", name, "macro"),
                    f"#{axis.macro} is already the macro of axis {macros[axis.macro]}; "
                    "each axis needs its own",
                )
            macros[axis.macro] = name
        first = next(iter(self.axes.values()))
        for key in AXIS_WRITE_KEYS:  # a frozen section: set once, here, as pydantic does
            self.__dict__[key] = getattr(first, key)
        return self

    @model_validator(mode="after")
    def _own_roles(self) -> CompensationSection:
        """The handshake, probe and alive macros are none of the axes' macros nor each other."""
        roles = {
            axis.macro: "macro" if self.axes is None else f"macro of axis {name}"
            for name, axis in self.axis_writes().items()
        }
        for role in ("handshake_macro", "probe_macro", "alive_macro"):
            number = getattr(self, role)
            if number is None:
                continue
            if number in roles:
                raise KeyPathError(
                    (role,), f"#{number} is already the {roles[number]}; give its own"
                )
            roles[number] = role
        return self

    def axis_writes(self) -> dict[str, AxisWrite]:
        """Each axis's write settings by axis name (the single-axis form: one, Z)."""
        if self.axes is None:
            return {SINGLE_AXIS: self}
        return dict(self.axes)


class OnlineCorrectionSection(Strict):
    """The probe-driven online correction (:mod:`models.online.correction`).

    Off by default. When on, every new value of ``compensation.probe_macro``
    updates a Kalman filter on the model's residual; the correction is added to
    the prediction before the compensation policy's clamp and slew limit.
    """

    enabled: bool = False
    kind: Literal["bias", "bias-rate", "bias-gain"] = "bias"
    process_um2_per_h: float = Field(default=1.0, ge=0)
    rate_process_um2_per_h3: float = Field(default=0.0, ge=0)
    gain_process_per_h: float = Field(default=0.0, ge=0)
    gain_prior: float = Field(default=0.5, gt=0)
    reversion_tau_s: float | None = Field(default=None, gt=0)
    probe_noise_um: float = Field(default=0.3, gt=0)
    bound_um: float = Field(default=20.0, gt=0)
    outlier_sigma: float = Field(default=4.0, gt=0)
    decay_after_s: float = Field(default=14400.0, ge=0)
    decay_tau_s: float = Field(default=3600.0, gt=0)
    reset_after_refusals: int = Field(default=2, ge=1)

    def params(self) -> CorrectionParams:
        return CorrectionParams.from_dict(self.model_dump(exclude={"enabled"}))


class MonitorSection(MonitorParams, Strict):
    """The residual monitor (:mod:`gateway.live.proposal_monitor`; its tests in
    :mod:`models.online.residual_monitor`).

    Off by default. When on, every probe's innovation goes to the sequential
    tests; an alarm starts a background residual analysis of the logged history,
    and an effect it believes is published as a proposal in the model store.
    """

    enabled: bool = False
    false_alarms_per_month: float = Field(default=1.0, gt=0, le=100)  # at most ~3 a day
    #: random walk of the monitor's own filter, µm²/h (slower than the correction's)
    process_um2_per_h: float = Field(default=0.1, ge=0)
    history_days: float = Field(default=30.0, gt=0, le=365)
    min_history_probes: int = Field(default=24, ge=10)
    method: Literal["mlr", "grey-mlr", "pca-quadratic"] = "mlr"

    def params(self) -> MonitorParams:
        return MonitorParams.model_validate(
            self.model_dump(include=set(MonitorParams.model_fields))
        )


class BandSection(Strict):
    name: str
    min_rpm: float = Field(ge=0)
    max_rpm: float = Field(gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> BandSection:
        if self.min_rpm >= self.max_rpm:
            raise KeyPathError(
                ("min_rpm",),
                f"{self.min_rpm:g} r/min must be below max_rpm ({self.max_rpm:g} r/min)",
            )
        return self


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

    @model_validator(mode="after")
    def _rules(self) -> RegimeSection:
        try:
            self.rules()
        except ValueError as exc:
            raise _located(exc, "RegimeRules") from None
        return self


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
    #: stated accuracy of the temperature sensors, ± °C (models.fit.conditioning)
    sensor_accuracy_C: float = Field(default=DEFAULT_SENSOR_ACCURACY_C, gt=0, le=10)
    #: a model that one sensor off by its accuracy would move by more is refused, µm
    max_bias_error_um: float = Field(default=DEFAULT_MAX_BIAS_ERROR_UM, gt=0, le=1000)
    #: promote a new proposal of the residual monitor without an operator
    #: (gateway.live.bank.promotion)
    auto_promote: bool = False
    #: HMAC key the store's models must be signed with (models.signing); outside the store.
    #: Default: $SPINDLE_MODEL_KEY_FILE, else $XDG_CONFIG_HOME/spindle-gateway/model-signing.key
    signing_key_file: Path | None = None
    #: the store's models are signed and checked; false: an unsigned store (nothing checked)
    signing: bool = True

    @model_validator(mode="after")
    def _key_outside_the_store(self) -> ModelsSection:
        key = self.signing_key_file
        if key is not None and not self.signing:
            raise KeyPathError(
                ("signing_key_file",),
                f"{key} is named, but models.signing is false (an unsigned store): "
                "remove one of the two",
            )
        if key is not None and key.resolve().is_relative_to(self.store.resolve()):
            raise KeyPathError(
                ("signing_key_file",),
                f"{key} is inside the model store {self.store}: keep the key where whoever "
                "can write models cannot read it",
            )
        return self


class MachineSection(Strict):
    id: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    cycle_s: float = Field(default=1.0, gt=0)
    transmitters: list[BusSection] = Field(min_length=1)
    sensors: dict[str, SensorSection] = Field(default_factory=dict)
    cnc: CncSection
    compensation: CompensationSection = CompensationSection()
    online_correction: OnlineCorrectionSection = OnlineCorrectionSection()
    monitor: MonitorSection = MonitorSection()
    models: ModelsSection
    plausibility: QualitySection = QualitySection()

    @model_validator(mode="after")
    def _sensor_names(self) -> MachineSection:
        names = [c for bus in self.transmitters for d in bus.devices for c in d.channels if c]
        seen: set[str] = set()
        for b, bus in enumerate(self.transmitters):
            for d, device in enumerate(bus.devices):
                for c, name in enumerate(device.channels):
                    if name in seen:
                        raise KeyPathError(
                            ("transmitters", b, "devices", d, "channels", c),
                            f"sensor '{name}' is already on another channel; one channel each",
                        )
                    if name:
                        seen.add(name)
        unknown = sorted(set(self.sensors) - set(names))
        if unknown:
            raise KeyPathError(
                ("sensors", unknown[0]),
                f"sensors {unknown} are configured but on no transmitter channel",
            )
        comp = self.compensation
        used = [m for m in (comp.handshake_macro, comp.probe_macro) if m is not None]
        if comp.macro in used:
            raise ValueError(f"macro #{comp.macro} is used twice in compensation")
        if self.online_correction.enabled and comp.probe_macro is None:
            raise ValueError("online_correction.enabled needs compensation.probe_macro")
        if self.monitor.enabled and comp.probe_macro is None:
            raise ValueError("monitor.enabled needs compensation.probe_macro")
        return self

    @model_validator(mode="after")
    def _axes_models(self) -> MachineSection:
        """With ``compensation.axes`` each axis names its own models; the regime rules
        (bands, window) stay shared, and no model serves two axes."""
        axes = self.compensation.axes
        if axes is None:
            return self
        regimes = self.models.regimes
        for key in ("models", "fallback_model"):
            if key in regimes.model_fields_set:
                raise KeyPathError(
                    ("models", "regimes", key),
                    "with compensation.axes each axis names its models "
                    f"(compensation.axes.<A>.{key}); leave it out here",
                )
        serving: dict[str, str] = {}
        for name, axis in axes.items():
            try:
                dataclasses.replace(
                    regimes.rules(), models=dict(axis.models), fallback_model=axis.fallback_model
                )
            except ValueError as exc:
                message = str(exc).removeprefix("RegimeRules.models: ")
                raise KeyPathError(("compensation", "axes", name, "models"), message) from None
            for key, model_id in axis.named_models().items():
                other = serving.setdefault(model_id, name)
                if other != name:
                    raise KeyPathError(
                        ("compensation", "axes", name, *key.split(".")),
                        f"model '{model_id}' already serves axis {other}: a model predicts "
                        "one axis's error",
                    )
        return self

    def axis_sections(self) -> dict[str, AxisSection]:
        """Every axis compensated, by name, in the order written each cycle: the axes of
        ``compensation.axes``, or the single-axis form as one axis named Z (its models
        those of ``models.regimes``)."""
        comp = self.compensation
        if comp.axes is not None:
            return dict(comp.axes)
        regimes = self.models.regimes
        single = AxisSection.model_construct(
            **{key: getattr(comp, key) for key in AXIS_WRITE_KEYS},
            target=None,
            models=dict(regimes.models),
            fallback_model=regimes.fallback_model,
        )
        return {SINGLE_AXIS: single}

    @model_validator(mode="after")
    def _fits_sensors_and_cycle(self) -> MachineSection:
        """One missed read must not make a sensor stale; a fixed reference covers every sensor."""
        for name in self.sensor_names:
            sensor = self.sensors.get(name)
            if sensor is None or "stale_s" not in sensor.model_fields_set:
                continue
            if sensor.stale_s < self.cycle_s:
                raise KeyPathError(
                    ("sensors", name, "stale_s"),
                    f"{sensor.stale_s:g} s is shorter than cycle_s ({self.cycle_s:g} s): "
                    "one missed read would make the sensor stale; at least cycle_s expected",
                )
        reference = self.models.reference
        unknown = sorted(set(reference.values_C) - set(self.sensor_names))
        if unknown:
            raise KeyPathError(
                ("models", "reference", "values_C", unknown[0]),
                f"no transmitter channel carries sensor(s) {unknown}",
            )
        if reference.mode == "fixed":
            missing = [n for n in self.sensor_names if n not in reference.values_C]
            if missing:
                raise KeyPathError(
                    ("models", "reference", "values_C"),
                    f"mode 'fixed' needs a reference temperature (°C) for every sensor; "
                    f"missing: {missing}",
                )
        try:
            self.quality_limits()
        except ValueError as exc:
            raise KeyPathError(("sensors",), str(exc)) from None
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
                stale_s=s.stale_s if "stale_s" in s.model_fields_set else self.default_stale_s,
            )
        return limits

    @property
    def default_stale_s(self) -> float:
        """``stale_s`` of a sensor that sets none: 10 s, or two cycles if that is longer."""
        return max(SensorSection().stale_s, 2 * self.cycle_s)

    def cnc_address(self) -> tuple[str, int | None, int | None]:
        """(host, port, Modbus device id) of the CNC: two machines with the same are one CNC."""
        if self.cnc.opcua is not None:
            host, port = _host_port(self.cnc.opcua.endpoint)
            return _same_host(host), port or 4840, None
        modbus = self.cnc.modbus
        assert modbus is not None
        return _same_host(modbus.host), modbus.port, modbus.device_id

    def written_macros(self) -> dict[str, int]:
        """The macro variables the gateway writes on this machine's CNC, by key (below
        ``compensation``, dotted: ``axes.X.macro``)."""
        comp = self.compensation
        if comp.axes is None:
            written = {"macro": comp.macro}
        else:
            written = {f"axes.{name}.macro": axis.macro for name, axis in comp.axes.items()}
        if comp.handshake_macro is not None:
            written["handshake_macro"] = comp.handshake_macro
        if comp.alive_macro is not None:
            written["alive_macro"] = comp.alive_macro
        return written


def _same_host(host: str) -> str:
    return "127.0.0.1" if host.lower() == "localhost" else host.lower()


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
        value = default if literal is None else literal
        if value is None:  # the section's validator refuses this before any value is read
            raise ConfigError(f"give '{key}' or '{key}_env' (an environment variable)")
        return value

    def url_value(self) -> str:
        url = self._setting("url")
        if self.url_env is not None and urlsplit(url).scheme not in ("http", "https"):
            raise ConfigError(
                f"environment variable {self.url_env} (url_env): expected an http:// or "
                f"https:// URL, got '{url}'"
            )
        return url

    def org_value(self) -> str:
        return self._setting("org", "-")  # InfluxDB 1.8 takes any org

    def bucket_value(self) -> str:
        return self._setting("bucket")

    @field_validator("url")
    @classmethod
    def _http_url(cls, value: str | None) -> str | None:
        if value is None:
            return None  # from url_env, checked when it is read
        if urlsplit(value).scheme not in ("http", "https"):
            raise ValueError(f"expected an http:// or https:// URL, got '{value}'")
        _host_port(value)
        return value

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
    nothing. Without it: points go to the embedded ``local_store`` (SQLite for the
    open period, Parquet parts beside it for closed ones).
    """

    influxdb: InfluxSection | None = None
    local_store: Path = Path(".cache/data/points.sqlite")
    buffer_path: Path = Path(".cache/data/buffer.sqlite")
    buffer_max_points: int = Field(default=2_000_000, ge=1000)
    # Retention (deploy/README.md, "Disk use"): points older than *_retention_days go,
    # and the oldest go while a file holds more than *_max_mb (10⁶ bytes), checked every
    # retention_interval_s. Defaults: a 16 GB edge disk; the local store keeps the 1-s
    # points 180 days and their per-minute history for years: a year of ten machines
    # at 1 Hz projects to 4.6 GB (docs/benchmarks.md); the buffer days (~150 bytes a point).
    local_store_retention_days: float = Field(default=180.0, gt=0)
    local_store_max_mb: float = Field(default=8000.0, ge=1)
    # The local store's per-minute history (min/mean/max of every number) outlives its
    # 1-s points: kept this long, and dropped last when the store is at its size cap.
    local_store_history_days: float = Field(default=3650.0, gt=0)
    buffer_retention_days: float = Field(default=30.0, gt=0)
    buffer_max_mb: float = Field(default=1000.0, ge=1)
    retention_interval_s: float = Field(default=60.0, gt=0)


class ScadaUserSection(Credentials):
    username: str  # the login name  # type: ignore[assignment]
    role: Literal["operator", "viewer"] = "viewer"


class ScadaSection(Strict):
    """The gateway's own OPC UA server for SCADA (Basic256Sha256 SignAndEncrypt only).

    ``host`` 0.0.0.0 serves every interface (a container); client certificates
    must be copied into ``<pki_dir>/trusted`` (see docs/scada.md).
    """

    host: str = "127.0.0.1"
    port: int = Field(default=4841, ge=1, le=65535)
    pki_dir: Path = Path(".cache/state/pki")
    allow_anonymous: bool = False
    users: list[ScadaUserSection] = Field(default_factory=list)
    rejected_keep: int = Field(default=50, ge=1, le=10_000)
    login_max_failures: int = Field(default=5, ge=1, le=1000)
    login_window_s: float = Field(default=60.0, gt=0, le=86_400)
    login_lockout_s: float = Field(default=30.0, gt=0, le=86_400)
    login_max_lockout_s: float = Field(default=900.0, gt=0, le=86_400)

    @model_validator(mode="after")
    def _lockout_bounds(self) -> ScadaSection:
        if self.login_lockout_s > self.login_max_lockout_s:
            raise ValueError(
                f"login_lockout_s ({self.login_lockout_s}) must not exceed "
                f"login_max_lockout_s ({self.login_max_lockout_s})"
            )
        return self


class WebSection(Strict):
    """The operator console in the browser (gateway/web, docs/console.md).

    ``users``: the accounts and roles of ``scada.users`` when not given here.
    ``tls_cert``/``tls_key`` (PEM) serve HTTPS; both or neither. ``reports_dir``:
    where ``analyze --report`` output is kept, browsable from the console.
    """

    host: str = "127.0.0.1"
    port: int = Field(default=8080, ge=1, le=65535)
    tls_cert: Path | None = None
    tls_key: Path | None = None
    users: list[ScadaUserSection] | None = None
    reports_dir: Path | None = None
    session_hours: float = Field(default=12.0, gt=0, le=24 * 30)
    login_max_failures: int = Field(default=5, ge=1, le=1000)
    login_window_s: float = Field(default=60.0, gt=0, le=86_400)
    login_lockout_s: float = Field(default=30.0, gt=0, le=86_400)
    login_max_lockout_s: float = Field(default=900.0, gt=0, le=86_400)

    @model_validator(mode="after")
    def _tls_pair(self) -> WebSection:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together: give both or neither")
        if self.login_lockout_s > self.login_max_lockout_s:
            raise ValueError(
                f"login_lockout_s ({self.login_lockout_s}) must not exceed "
                f"login_max_lockout_s ({self.login_max_lockout_s})"
            )
        return self


class SparkplugCommandsSection(Strict):
    """Which Sparkplug device commands (DCMD) the gateway acts on; each off unless set."""

    set_compensation: bool = False
    promote_proposal: bool = False
    rollback_models: bool = False


class SparkplugSection(Credentials):
    """The gateway as a Sparkplug B edge node (gateway/sparkplug, docs/fleet.md).

    ``brokers`` are tried in turn (fail-over): ``mqtt://host:port`` or, with TLS,
    ``mqtts://host:port`` (``ca_file``, and ``cert_file``/``key_file`` for a client
    certificate). The password comes from ``password_env`` or ``password_file``.
    """

    brokers: list[str] = Field(min_length=1)
    group_id: str
    edge_node_id: str
    primary_host_id: str | None = None
    client_id: str | None = None
    qos: Literal[0, 1] = 0  # births and data; Sparkplug 3.0 asks QoS 0 (docs/fleet.md)
    keepalive_s: int = Field(default=30, ge=5, le=3600)
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None
    startup_delay_max_s: float = Field(default=5.0, ge=0, le=600)
    reconnect_max_s: float = Field(default=30.0, gt=0, le=3600)
    buffer_path: Path = Path(".cache/state/sparkplug-buffer.sqlite")
    buffer_max_points: int = Field(default=1_000_000, ge=1)
    commands: SparkplugCommandsSection = SparkplugCommandsSection()

    @model_validator(mode="after")
    def _checked(self) -> SparkplugSection:
        from gateway.sparkplug.topics import check_id

        for key in ("group_id", "edge_node_id", "primary_host_id"):
            value = getattr(self, key)
            if value is not None:
                try:
                    check_id(value, key)
                except ValueError as exc:
                    raise KeyPathError((key,), str(exc)) from None
        for index, url in enumerate(self.brokers):
            if urlsplit(url).scheme not in ("mqtt", "mqtts"):
                raise KeyPathError(
                    ("brokers", index), f"'{url}': expected mqtt://host:port or mqtts://host:port"
                )
            try:
                _host_port(url)
            except ValueError as exc:
                raise KeyPathError(("brokers", index), str(exc)) from None
        if self.key_file is not None and self.cert_file is None:
            raise KeyPathError(("key_file",), "a key_file needs its cert_file")
        return self


class GatewayConfig(Strict):
    machines: list[MachineSection] = Field(min_length=1)
    #: One line per old key name the file still uses (file, line, the new name).
    _deprecations: list[str] = PrivateAttr(default_factory=list)
    #: The file it was read from, to locate later refusals (a model store's) on its lines.
    _document: YamlDocument | None = PrivateAttr(default=None)
    state_dir: Path = Path(".cache/state")
    logging: LoggingSection = LoggingSection()
    scada: ScadaSection | None = None
    sparkplug: SparkplugSection | None = None
    web: WebSection | None = None
    simulator: dict[str, Any] | None = None  # checked by simulator.serve
    # The runtime's event loop (gateway/process/event_loop.py): uvloop, or asyncio's own.
    event_loop: EventLoopName = DEFAULT_EVENT_LOOP

    @property
    def deprecations(self) -> list[str]:
        """Old key names the file used, one located line each (empty for a current file)."""
        return list(self._deprecations)

    def error_at(self, loc: Loc, message: str) -> ConfigError:
        """``message`` located at ``loc`` of the file this configuration was read from
        (``file:line: key.path: message``); unlocated for one built in code."""
        if self._document is None:
            return ConfigError(message)
        return ConfigError(str(self._document.error(loc, message)))

    @model_validator(mode="after")
    def _unique_ids(self) -> GatewayConfig:
        ids = [m.id for m in self.machines]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"machine id(s) {duplicates} used twice")
        return self

    @model_validator(mode="after")
    def _one_setting_per_line(self) -> GatewayConfig:
        """Buses on one serial port are one RS-485 line (:func:`check_shared_lines`)."""
        check_shared_lines(self.machines)
        return self

    @model_validator(mode="after")
    def _one_writer_per_macro(self) -> GatewayConfig:
        """Two machines writing one macro of one CNC would overwrite each other every cycle."""
        writers: dict[tuple[object, ...], tuple[int, str]] = {}
        for index, machine in enumerate(self.machines):
            address = machine.cnc_address()
            for key, number in machine.written_macros().items():
                owner = writers.get((*address, number))
                if owner is not None:
                    host, port, _ = address
                    raise KeyPathError(
                        ("machines", index, "compensation", *key.split(".")),
                        f"#{number} of the CNC at {host}:{port} is already written by machine "
                        f"'{owner[1]}' (machines[{owner[0]}]); each macro needs one writer",
                    )
                writers[(*address, number)] = (index, machine.id)
        return self

    @model_validator(mode="after")
    def _alive_count_not_read_as_probe(self) -> GatewayConfig:
        """The alive count changes every cycle: in another machine's probe macro on the same
        CNC it would be read as a new measurement of the error each cycle."""
        probes = {
            (*m.cnc_address(), m.compensation.probe_macro): (i, m.id)
            for i, m in enumerate(self.machines)
            if m.compensation.probe_macro is not None
        }
        for index, machine in enumerate(self.machines):
            number = machine.compensation.alive_macro
            if number is None:
                continue
            reader = probes.get((*machine.cnc_address(), number))
            if reader is None or reader[0] == index:
                continue
            host, port, _ = machine.cnc_address()
            raise KeyPathError(
                ("machines", index, "compensation", "alive_macro"),
                f"#{number} of the CNC at {host}:{port} is the probe_macro of machine "
                f"'{reader[1]}' (machines[{reader[0]}]); the alive count needs its own macro",
            )
        return self

    @model_validator(mode="after")
    def _one_key_per_store(self) -> GatewayConfig:
        """A store's models are checked with one key (models.signing keys it by store): a
        machine naming none, or another one, would silently replace the key of a machine
        sharing its store, whose promotions would then go unchecked."""
        keys: dict[Path, tuple[int, str, str]] = {}
        for index, machine in enumerate(self.machines):
            store = machine.models.store.resolve()
            named = _signing_named(machine.models)
            first = keys.setdefault(store, (index, machine.id, named))
            if first[2] != named:
                raise KeyPathError(
                    ("machines", index, "models", "signing_key_file"),
                    f"machine '{machine.id}' names {named}, but shares the model store "
                    f"{machine.models.store} with machine '{first[1]}' (machines[{first[0]}]), "
                    f"which names {first[2]}; machines sharing a store name the same key",
                )
        return self


def login_limits(section: ScadaSection | WebSection) -> LoginLimits:
    """The lockout of repeated failed logins a section's ``login_*`` keys set (the SCADA
    server's or the console's), built here once for both, like the other limits."""
    return LoginLimits(
        max_failures=section.login_max_failures,
        window_s=section.login_window_s,
        lockout_s=section.login_lockout_s,
        max_lockout_s=section.login_max_lockout_s,
    )


def _signing_named(models: ModelsSection) -> str:
    """How a machine's ``models`` section names its store's signing, to compare machines."""
    if not models.signing:
        return "models.signing: false"
    key = models.signing_key_file
    return "none" if key is None else f"signing key {key.resolve()}"


def load_config(path: str | Path, *, check_host: bool = False) -> GatewayConfig:
    """The configuration in ``path``, validated; any problem is one located :class:`ConfigError`.

    ``check_host`` also checks what depends on this host (secrets set and
    readable, folders writable): ``check-config`` and ``run`` do, so that
    ``run`` never refuses later what ``check-config`` let through.
    """
    try:
        document = load_yaml(path)
        if document.data is None:
            raise YamlError(
                f"{document.path}:1: no settings (the file is empty or only comments); "
                "a mapping with a 'machines' list was expected"
            )
        if not isinstance(document.data, dict):
            kind = "a list" if isinstance(document.data, list) else "a single value"
            raise YamlError(
                f"{document.path}:1: {kind} at the top level; a mapping with a 'machines' "
                "list was expected"
            )
        deprecations = rename_old_keys(document)
        config = validate_section(document, GatewayConfig)
        config._deprecations = deprecations
        config._document = document
        if config.simulator is not None:
            from simulator.serve import SimulatorConfig

            validate_section(document, SimulatorConfig, ("simulator",))
        if check_host:
            check_host_of(config, document)
    except YamlError as exc:
        raise ConfigError(str(exc)) from None
    return config


#: Machine keys renamed, old name → new name; the old name is read as the new one.
RENAMED_MACHINE_KEYS = {"quality": "plausibility"}


def rename_old_keys(document: YamlDocument) -> list[str]:
    """Read a machine's old key names as the new ones (in ``document``, lines kept).

    ``machines[].quality`` configured cross-sensor plausibility while the range,
    rate and stuck limits sit under ``sensors.<name>``; it is ``plausibility`` now.
    A file with the old name still loads; the one line returned names the file, the
    line of its first use and the new name. Both names in one machine are refused.
    """
    machines = document.data.get("machines") if isinstance(document.data, dict) else None
    if not isinstance(machines, list):
        machines = []
    notes: list[str] = []
    for old, new in RENAMED_MACHINE_KEYS.items():
        used = [i for i, m in enumerate(machines) if isinstance(m, dict) and old in m]
        for i in used:
            if new in machines[i]:
                raise document.error(
                    ("machines", i, old), f"both '{old}' and '{new}' given; keep '{new}' only"
                )
            machines[i][new] = machines[i].pop(old)
            for loc, line in list(document.lines.items()):
                if loc[:3] == ("machines", i, old):
                    document.lines[("machines", i, new, *loc[3:])] = line
        if used:
            others = f" (and {len(used) - 1} more machine(s))" if len(used) > 1 else ""
            notes.append(
                f"{document.locate(('machines', used[0], old))}: deprecated key name{others}; "
                f"rename it to '{new}' (machines[].{new}), same settings"
            )
    return notes


def check_host_of(config: GatewayConfig, document: YamlDocument) -> None:
    """Secrets and folders, as ``run`` will use them; the first problem, located."""
    problems = _secret_reference_problems(config)
    for index, machine in enumerate(config.machines):
        if machine.cnc.opcua is not None and machine.cnc.opcua.security is not None:
            security = ("machines", index, "cnc", "opcua", "security")
            problems += _security_problems(machine.cnc.opcua.security, security)
    if config.scada is not None:
        problems += _folder_problems(config.scada.pki_dir, ("scada", "pki_dir"))
    problems += _folder_problems(Path(config.state_dir), ("state_dir",))
    logging = config.logging
    if logging.influxdb is not None:
        problems += _file_problems(logging.buffer_path, ("logging", "buffer_path"))
    else:
        problems += _file_problems(logging.local_store, ("logging", "local_store"))
    problems += _named_path_problems(config)
    if problems:
        loc, message = problems[0]
        raise document.error(loc, message)


def _secret_reference_problems(config: GatewayConfig) -> list[tuple[Loc, str]]:
    """Every secret the configuration names, read as ``run`` will read it: each
    ``*_env`` set and not empty, each secret or key file there, readable and not empty,
    each account with a password (a user without one would log in with an empty one), and
    each certificate, key and model signing key file readable."""
    problems: list[tuple[Loc, str]] = []
    for index, machine in enumerate(config.machines):
        if machine.cnc.opcua is not None:
            problems += _secret_problems(machine.cnc.opcua, ("machines", index, "cnc", "opcua"))
        keys: tuple[str, ...] = ("signing_key_file",)
        problems += _key_file_problems(machine.models, ("machines", index, "models"), keys)
    if config.scada is not None:
        problems += _account_problems(config.scada.users, ("scada", "users"))
    if config.web is not None:
        problems += _account_problems(config.web.users or [], ("web", "users"))
        problems += _key_file_problems(config.web, ("web",), ("tls_cert", "tls_key"))
    if config.sparkplug is not None:
        problems += _secret_problems(config.sparkplug, ("sparkplug",))
        keys = ("ca_file", "cert_file", "key_file")
        problems += _key_file_problems(config.sparkplug, ("sparkplug",), keys)
    if config.logging.influxdb is not None:
        problems += _token_problems(config.logging.influxdb, ("logging", "influxdb"))
    return problems


def _secret_problems(credentials: Credentials, loc: Loc) -> list[tuple[Loc, str]]:
    key = "password_env" if credentials.password_env else "password_file"
    try:
        secret = credentials.password()
    except ConfigError as exc:
        return [((*loc, key), str(exc))]
    if secret == "" and credentials.password_file is not None:
        return [((*loc, key), f"password_file {credentials.password_file} is empty")]
    if secret == "" and credentials.password_env:
        message = f"environment variable {credentials.password_env} (password_env) is empty"
        return [((*loc, key), message)]
    return []


def _account_problems(users: Sequence[ScadaUserSection], loc: Loc) -> list[tuple[Loc, str]]:
    """Each login account's password: named, and there."""
    problems: list[tuple[Loc, str]] = []
    for index, user in enumerate(users):
        if not user.password_env and user.password_file is None:
            message = f"user '{user.username}' has no password: give password_env or password_file"
            problems.append(((*loc, index, "username"), message))
        else:
            problems += _secret_problems(user, (*loc, index))
    return problems


def _token_problems(influxdb: InfluxSection, loc: Loc) -> list[tuple[Loc, str]]:
    key = "token_env" if influxdb.token_env else "token_file"
    try:
        token = influxdb.token()
    except ConfigError as exc:
        return [((*loc, key), str(exc))]
    if token == "" and influxdb.token_env:
        return [((*loc, key), f"environment variable {influxdb.token_env} (token_env) is empty")]
    if token == "" and influxdb.token_file is not None:
        return [((*loc, key), f"token_file {influxdb.token_file} is empty")]
    return []


def _key_file_problems(section: object, loc: Loc, keys: Sequence[str]) -> list[tuple[Loc, str]]:
    """Certificates and keys the section names: files there and readable."""
    problems: list[tuple[Loc, str]] = []
    for key in keys:
        path: Path | None = getattr(section, key)
        if path is None:
            continue
        try:
            with path.open("rb") as file:
                file.read(1)
        except OSError as exc:
            problems.append(((*loc, key), f"{path}: {exc.strerror or exc}"))
    return problems


def _security_problems(security: OpcUaSecuritySection, loc: Loc) -> list[tuple[Loc, str]]:
    """The client certificate and key both present, or both absent and creatable; a pinned
    server certificate present."""
    pair = {"certificate": security.certificate, "private_key": security.private_key}
    present = {key: path.is_file() for key, path in pair.items()}
    if present["certificate"] != present["private_key"]:
        missing = next(key for key, there in present.items() if not there)
        other = pair["private_key" if missing == "certificate" else "certificate"]
        there = (
            "is a folder, but {} is a file"
            if pair[missing].is_dir()
            else "does not exist, but {} does"
        )
        return [
            (
                (*loc, missing),
                f"{pair[missing]} {there.format(other)}: "
                "give both, or neither to have them made on the first connect",
            )
        ]
    problems: list[tuple[Loc, str]] = []
    if not present["certificate"]:
        for key, path in pair.items():
            problems += _file_problems(path, (*loc, key))
    pinned = security.server_certificate
    if pinned is not None and not pinned.is_file():
        problems.append(((*loc, "server_certificate"), f"{pinned} {_absent(pinned)}"))
    return problems


def _absent(path: Path) -> str:
    """Why a file the configuration names is not one: a folder there, or nothing."""
    return "is a folder, not a file" if path.is_dir() else "does not exist"


def _folder_problems(folder: Path, loc: Loc, subject: Path | None = None) -> list[tuple[Loc, str]]:
    """A folder the gateway can create or write in (for ``subject``); else why not."""
    subject = folder if subject is None else subject
    existing = folder
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if not existing.is_dir():
        what = "is" if existing == subject else f"would be inside {existing}, which is"
        return [(loc, f"{subject} {what} a file; a folder the gateway can write in was expected")]
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        return [(loc, f"{subject}: cannot be created in {existing} ({exc.strerror or exc})")]
    return []


def _file_problems(path: Path, loc: Loc) -> list[tuple[Loc, str]]:
    """A file the gateway can create or write."""
    if path.is_dir():
        return [(loc, f"{path} is a folder; a file the gateway can write was expected")]
    if path.exists() and not os.access(path, os.W_OK):
        return [(loc, f"{path} is not writable")]
    return _folder_problems(path.parent, loc, subject=path)


def _named_path_problems(config: GatewayConfig) -> list[tuple[Loc, str]]:
    """The signing keys, folders and buffers the sections name, as ``run`` will open them:
    each refused here on its own line rather than by ``run`` later, unlocated. (The model
    stores are refused, located, by :func:`gateway.wiring.load_located_bank`.)"""
    problems: list[tuple[Loc, str]] = []
    for index, machine in enumerate(config.machines):
        key = machine.models.signing_key_file
        if key is not None:
            loc = ("machines", index, "models", "signing_key_file")
            problems += _readable_problems(key, loc, "key")
    reports = None if config.web is None else config.web.reports_dir
    if reports is not None and reports.exists() and not reports.is_dir():
        problems.append(
            (("web", "reports_dir"), f"{reports} is a file; a folder of reports was expected")
        )
    if config.sparkplug is not None:
        problems += _file_problems(config.sparkplug.buffer_path, ("sparkplug", "buffer_path"))
    return problems


def _readable_problems(path: Path, loc: Loc, kind: str) -> list[tuple[Loc, str]]:
    """A file the gateway reads at start (a key, a certificate), there and readable."""
    if not path.exists():
        return [(loc, f"{path} does not exist; a readable {kind} file was expected")]
    if not path.is_file():
        return [(loc, f"{path} is a folder; a readable {kind} file was expected")]
    if not os.access(path, os.R_OK):
        return [(loc, f"{path} is not readable by this user; a readable {kind} file was expected")]
    return []


# --------------------------------------------------------------------------- RS-485 lines
# Which transmitter buses of the configuration are one physical RS-485 line.
#
# Which transmitter buses of the configuration are one physical RS-485 line.
#
# A line is named by its serial port path: every bus section (of any machine)
# that gives the same ``rtu.port`` is on that line and reads through one
# :class:`drivers.bus_hub.BusHub`. No new key is needed, but the sections must
# agree: one line has one baud rate and one parity, and one device id answers on
# it once (two sections naming the same id would read the same module, or two
# modules would answer one request and garble each other's replies). Those are
# refused by :func:`check_shared_lines`, located on the second section.
#
# What may differ is taken at its most patient: the line's request timeout is the
# longest any of its sections asks, the inter-frame silence the longest of the
# RTU t3.5 at the line's baud rate and every ``rtu.min_silence_s``.
#
# Modbus TCP buses keep one connection each: a TCP server carries concurrent
# connections and tells replies apart by transaction id, so nothing collides.

Where = tuple[str | int, ...]


def rtu_buses(machines: Sequence[MachineSection]) -> dict[str, list[tuple[Where, BusSection]]]:
    """Bus sections by serial port path, each with its key path in the configuration."""
    lines: dict[str, list[tuple[Where, BusSection]]] = {}
    for m, machine in enumerate(machines):
        for b, bus in enumerate(machine.transmitters):
            if bus.rtu is not None:
                lines.setdefault(bus.rtu.port, []).append((("machines", m, "transmitters", b), bus))
    return lines


def check_shared_lines(machines: Sequence[MachineSection]) -> None:
    """Refuse two line settings or one device id twice on one port (:class:`KeyPathError`)."""
    for port, buses in rtu_buses(machines).items():
        first_where, first = buses[0]
        assert first.rtu is not None
        settings = {
            "baudrate": ("baud rate", "{} baud", "at {} baud"),
            "parity": ("parity", "parity {}", "with parity {}"),
        }
        owners: dict[int, Where] = {}
        for where, bus in buses:
            assert bus.rtu is not None
            for key, (what, given, runs) in settings.items():
                mine, theirs = getattr(bus.rtu, key), getattr(first.rtu, key)
                if mine != theirs:
                    raise KeyPathError(
                        (*where, "rtu", key),
                        f"{given.format(mine)} given, but port {port} already runs "
                        f"{runs.format(theirs)} for {_owner(machines, first_where)}; "
                        f"one RS-485 line has one {what}",
                    )
            for d, device in enumerate(bus.devices):
                owner = owners.get(device.device_id)
                if owner is not None:
                    raise KeyPathError(
                        (*where, "devices", d, "device_id"),
                        f"device {device.device_id} on port {port} is already read by "
                        f"{_owner(machines, owner)}; one device id per RS-485 line",
                    )
                owners[device.device_id] = (*where, "devices", d)


def _owner(machines: Sequence[MachineSection], where: Where) -> str:
    """``machine 'vmc-1' (machines[0].transmitters[0])`` for a key path below a machine."""
    machine = machines[int(where[1])]
    return f"machine '{machine.id}' ({format_path(where)})"
