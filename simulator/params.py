"""Machine parameters: the YAML schema, validated once, with units in every key.

Defaults live in ``simulator/machine.yaml``; a config file may override any
part of them (a deep merge). Files are read by :mod:`drivers.yaml_loader`, so a
bad value is refused with the file, the line and the key path.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from drivers.schema import Strict
from drivers.yaml_loader import YamlError, first_problem, format_path, load_yaml, validate

NODES = ("bearing", "shaft", "motor", "headstock", "column")
DEFAULTS = Path(__file__).with_name("machine.yaml")
EFFECTS = ("thermal_lag", "speed_direct", "ambient", "drift", "cooler")


class Convection(Strict):
    base: float = Field(gt=0)
    per_krpm: float = Field(ge=0)


class BearingHeat(Strict):
    coefficient_W: float = Field(ge=0)
    exponent: float = Field(gt=0)


class MotorHeat(Strict):
    idle_W: float = Field(ge=0)
    per_krpm_W: float = Field(ge=0)


class Sensor(Strict):
    location: str
    mix: dict[str, float]
    lag_s: float = Field(gt=0)
    offset_C: float = 0.0

    @field_validator("mix")
    @classmethod
    def _weights(cls, mix: dict[str, float]) -> dict[str, float]:
        return node_weights(mix)


def node_weights(mix: dict[str, float]) -> dict[str, float]:
    """A mix of the network's nodes: known nodes, weights ≥ 0 summing to 1."""
    unknown = set(mix) - set(NODES)
    if unknown:
        raise ValueError(f"unknown node(s) {sorted(unknown)}; nodes are {list(NODES)}")
    if abs(sum(mix.values()) - 1.0) > 1e-9 or min(mix.values()) < 0:
        raise ValueError(f"weights must be ≥ 0 and sum to 1, got {mix}")
    return mix


class AmbientSensor(Strict):
    location: str
    lag_s: float = Field(gt=0)


class Probe(Strict):
    noise_um: float = Field(ge=0)
    period_s: float = Field(gt=0)
    macro: int = Field(ge=500, le=999)


class Ageing(Strict):
    """Slow machine ageing in machine days (86 400 s of machine time since the start).

    Both rates are 0 by default (no ageing). ``preload_gain_per_day`` (1/day): a
    drifting bearing preload; the bearing's share of the Z growth is scaled by
    ``1 + preload_gain_per_day · days``. ``coolant_offset_um_per_day`` (µm/day): a
    growing coolant offset, an additive Z error of ``rate · days`` µm.
    ``start_days`` (days): the machine's age when the simulation starts.
    """

    preload_gain_per_day: float = 0.0
    coolant_offset_um_per_day: float = 0.0
    start_days: float = Field(default=0.0, ge=0)

    @property
    def active(self) -> bool:
        return self.preload_gain_per_day != 0.0 or self.coolant_offset_um_per_day != 0.0


class Compensation(Strict):
    macro: int = Field(ge=500, le=999)
    unit: Literal["mm", "um"]
    sign: Literal[1, -1]

    @property
    def um_per_unit(self) -> float:
        return 1000.0 if self.unit == "mm" else 1.0


AXIS_NAME = re.compile(r"^[XY]$")


class AxisFace(Strict):
    """One face of the head or column: a first-order lag of a mix of the network's nodes."""

    mix: dict[str, float]
    tau_s: float = Field(gt=0)

    @field_validator("mix")
    @classmethod
    def _weights(cls, mix: dict[str, float]) -> dict[str, float]:
        return node_weights(mix)


class AxisGrowth(Strict):
    """A growth across the machine (X or Y): ``um_per_K`` × (hot face − cold face).

    The two faces lag the network's nodes with their own mixes and time constants,
    so the growth follows a temperature *difference*, not the Z growth's sum of rises.
    ``column`` names its error column in recordings (``*_um``); the CNC takes its
    compensation at ``compensation.macro`` and the probe publishes its measured
    error at ``probe_macro``.
    """

    column: str = Field(pattern=r"^[a-z][a-z0-9_]*_um$")
    um_per_K: float
    hot_face: AxisFace
    cold_face: AxisFace
    compensation: Compensation
    probe_macro: int = Field(ge=500, le=999)


class ThermalLag(Strict):
    share: float = Field(gt=0, le=1)
    tau_s: float = Field(gt=0)


class SpeedDirect(Strict):
    um_per_krpm: float
    um_per_krpm2: float


class AmbientCycle(Strict):
    amplitude_C: float = Field(ge=0)
    period_s: float = Field(gt=0)


class Drift(Strict):
    um_per_h: float


class Cooler(Strict):
    amplitude_C: float = Field(ge=0)
    period_s: float = Field(gt=0)
    conductance_W_per_K: float = Field(gt=0)
    offset_C: float


class Effects(Strict):
    thermal_lag: ThermalLag
    speed_direct: SpeedDirect
    ambient: AmbientCycle
    drift: Drift
    cooler: Cooler


class MachineParams(Strict):
    name: str
    max_speed_rpm: float = Field(gt=0)
    ambient_C: float
    heat_capacity_J_per_K: dict[str, float]
    conductance_W_per_K: dict[str, float]
    convection_W_per_K: dict[str, Convection]
    bearing_heat: BearingHeat
    motor_heat: MotorHeat
    growth_um_per_K: dict[str, float]
    sensors: dict[str, Sensor]
    sensor_noise_C: float = Field(ge=0)
    ambient_sensor: AmbientSensor
    probe: Probe
    compensation: Compensation
    effects: Effects
    ageing: Ageing = Ageing()
    axes: dict[str, AxisGrowth] = Field(default_factory=dict)
    sub_step_s: float = Field(gt=0, le=60)

    @model_validator(mode="after")
    def _nodes_known(self) -> MachineParams:
        if set(self.heat_capacity_J_per_K) != set(NODES):
            raise ValueError(f"heat_capacity_J_per_K needs exactly the nodes {list(NODES)}")
        if set(self.convection_W_per_K) != set(NODES):
            raise ValueError(f"convection_W_per_K needs exactly the nodes {list(NODES)}")
        if any(c <= 0 for c in self.heat_capacity_J_per_K.values()):
            raise ValueError("heat capacities must be > 0")
        for pair, g in self.conductance_W_per_K.items():
            a, _, b = pair.partition("-")
            if a not in NODES or b not in NODES or a == b or g < 0:
                raise ValueError(f"conductance '{pair}': expected 'node-node' with g ≥ 0")
        if set(self.growth_um_per_K) - set(NODES):
            raise ValueError(
                f"growth_um_per_K: unknown nodes {set(self.growth_um_per_K) - set(NODES)}"
            )
        self._axes_distinct()
        return self

    def _axes_distinct(self) -> None:
        """Axis names X/Y; no two axes (nor Z) share a column, a compensation or probe macro."""
        columns, macros = {"error_um"}, {self.compensation.macro, self.probe.macro}
        for name, axis in self.axes.items():
            if not AXIS_NAME.match(name):
                raise ValueError(f"axes: '{name}': expected X or Y (Z is growth_um_per_K)")
            if axis.column in columns:
                raise ValueError(f"axes.{name}.column: '{axis.column}' is already used")
            for macro in (axis.compensation.macro, axis.probe_macro):
                if macro in macros:
                    raise ValueError(f"axes.{name}: macro #{macro} is already used")
                macros.add(macro)
            columns.add(axis.column)


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def merged_params(overrides: dict[str, Any] | None = None) -> MachineParams:
    """The defaults with ``overrides`` merged in; a bad value raises pydantic's ValidationError."""
    document = load_yaml(DEFAULTS)
    if not overrides:
        return validate(document, MachineParams)
    return MachineParams.model_validate(deep_merge(document.data, overrides))


def load_params(
    overrides: dict[str, Any] | None = None, source: str = "machine parameters"
) -> MachineParams:
    """The defaults, with ``overrides`` merged in, validated."""
    try:
        return merged_params(overrides)
    except ValidationError as exc:
        loc, message = first_problem(exc)
        raise ValueError(f"{source}: '{format_path(loc)}': {message}") from None


def load_params_file(path: Path) -> MachineParams:
    """The defaults with the overrides of a YAML file (``simulate --params``), located errors."""
    document = load_yaml(path)
    if document.data is None:
        return merged_params()
    if not isinstance(document.data, dict):
        raise YamlError(f"{path}:1: a mapping of machine parameters was expected")
    try:
        return merged_params(document.data)
    except ValidationError as exc:
        loc, message = first_problem(exc)
        raise document.error(loc, message) from None
