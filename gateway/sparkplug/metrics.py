"""What each machine (a Sparkplug device) publishes: its metrics and one cycle's values.

The metric set of a machine is fixed by its sensors, the health counters and, for a
machine configured with several axes, its axes, so the births (NBIRTH/DBIRTH) declare
every metric once with an alias that stays the same for the life of the process.

A multi-axis machine keeps every metric of one axis (holding its first axis's values)
and adds, per axis ``<A>``, ``Axes/<A>/<leaf>`` with the same leaves as the machine's
per-axis metrics (:data:`AXIS_LEAVES`), after the health counters so that the aliases of
the other metrics are those of a single-axis machine.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from gateway.live.record import CycleRecord
from gateway.outputs.health import integer_counters
from gateway.sparkplug.payload import BOOLEAN, DOUBLE, INT64, STRING, UINT64, MetricSpec, Value

BD_SEQ = "bdSeq"
REBIRTH = "Node Control/Rebirth"
ENABLED = "Compensation/Enabled"
PROMOTE = "Command/Promote Proposal"
ROLLBACK = "Command/Rollback Models"
CYCLES = "Health/cycles"

#: Aliases: node metrics below ``ALIAS_BLOCK``, device ``i`` from ``(i + 1) * ALIAS_BLOCK``.
ALIAS_BLOCK = 1000
#: bdSeq is an Int64 in the will and the NBIRTH; the rebirth switch has no alias, so that
#: any host can ask for births by its name (Sparkplug 3.0).
NODE_METRICS = (MetricSpec(BD_SEQ, INT64, 1), MetricSpec(REBIRTH, BOOLEAN, None))
NODE_HEALTH_ALIAS = 10  # the node's ``Health/…`` metrics from here
#: The metrics a host may write, with the value type each takes; every other is read-only.
WRITABLE = {REBIRTH: bool, ENABLED: bool, PROMOTE: str, ROLLBACK: bool}

_RECORD_METRICS = (
    ("Spindle/Speed", DOUBLE, "r/min"),
    ("Regime", STRING, ""),
    ("Model", STRING, ""),
    ("Prediction", DOUBLE, "µm"),
    ("Online Correction", DOUBLE, "µm"),
    ("Compensation/Target", DOUBLE, "µm"),
    ("Compensation/Applied", DOUBLE, "µm"),
    ("Compensation/Write Status", STRING, ""),
    (ENABLED, BOOLEAN, ""),
    ("Probe/Error", DOUBLE, "µm"),
    ("Probe/Residual", DOUBLE, "µm"),
    (PROMOTE, STRING, ""),
    (ROLLBACK, BOOLEAN, ""),
    ("Prediction/Interval", DOUBLE, "µm"),
    ("Prediction/Training Span", STRING, ""),
    ("Prediction/Outside Inputs", STRING, ""),
)


#: The per-axis metrics' leaves: each axis ``<A>`` of a multi-axis machine has
#: ``Axes/<A>/<leaf>``, with the value of its :class:`~gateway.live.record.AxisRecord`.
AXIS_LEAVES = (
    ("Model", STRING, "", "model_id"),
    ("Prediction", DOUBLE, "µm", "predicted_um"),
    ("Online Correction", DOUBLE, "µm", "correction_um"),
    ("Compensation/Target", DOUBLE, "µm", "target_um"),
    ("Compensation/Applied", DOUBLE, "µm", "applied_um"),
    ("Compensation/Write Status", STRING, "", "write_status"),
    ("Prediction/Interval", DOUBLE, "µm", "interval_um"),
    ("Prediction/Training Span", STRING, "", "training_span"),
    ("Prediction/Outside Inputs", STRING, "", "outside_inputs"),
)


def device_specs(
    index: int, sensors: Sequence[str], health_keys: Sequence[str], axes: Sequence[str] = ()
) -> list[MetricSpec]:
    """The metrics of the ``index``-th machine (with ``Axes/<A>/…`` for each of its
    ``axes`` when it has several), with aliases unique across the node."""
    named: list[tuple[str, int, str]] = []
    for sensor in sensors:
        named.append((f"Temperature/{sensor}", DOUBLE, "°C"))
        named.append((f"Temperature/{sensor}/Quality", STRING, ""))
    named.extend(_RECORD_METRICS)
    named.extend((f"Health/{key}", UINT64, "") for key in health_keys)
    for axis in axes:
        named.extend((f"Axes/{axis}/{leaf}", kind, unit) for leaf, kind, unit, _ in AXIS_LEAVES)
    if len(named) > ALIAS_BLOCK:
        raise ValueError(f"{len(named)} metrics of one machine: more than {ALIAS_BLOCK} aliases")
    base = (index + 1) * ALIAS_BLOCK
    return [MetricSpec(name, kind, base + i, unit) for i, (name, kind, unit) in enumerate(named)]


def node_specs(health_keys: Sequence[str]) -> list[MetricSpec]:
    """The node's own metrics (NBIRTH, NDATA): bdSeq, the rebirth switch and the gateway's
    process-wide counters as ``Health/<name>``, which belong to no one machine."""
    health = [
        MetricSpec(f"Health/{key}", UINT64, NODE_HEALTH_ALIAS + i)
        for i, key in enumerate(health_keys)
    ]
    if NODE_HEALTH_ALIAS + len(health) > ALIAS_BLOCK:
        raise ValueError(
            f"{len(health)} node health counters: more than the aliases below {ALIAS_BLOCK}"
        )
    return [*NODE_METRICS, *health]


def health_counters(health: Mapping[str, Any]) -> dict[str, int]:
    """The integer counters of a machine's health (:func:`gateway.outputs.health.integer_counters`),
    by name."""
    return dict(sorted(integer_counters(health).items()))


def snapshot(record: CycleRecord, health: Mapping[str, Any]) -> dict[str, Value]:
    """One cycle of one machine as metric values by name."""
    values: dict[str, Value] = {}
    for sensor, value in record.temperatures_C.items():
        values[f"Temperature/{sensor}"] = value
        values[f"Temperature/{sensor}/Quality"] = record.quality.get(sensor)
    residual = None
    if record.probe_error_um is not None and record.predicted_um is not None:
        residual = record.probe_error_um - record.predicted_um
    values.update(
        {
            "Spindle/Speed": record.speed_rpm,
            "Regime": record.regime,
            "Model": record.model_id,
            "Prediction": record.predicted_um,
            "Online Correction": record.correction_um,
            "Compensation/Target": record.target_um,
            "Compensation/Applied": record.applied_um,
            "Compensation/Write Status": record.write_status,
            ENABLED: bool(health.get("compensation_enabled", True)),
            "Probe/Error": record.probe_error_um,
            "Probe/Residual": residual,
            PROMOTE: "",
            ROLLBACK: False,
            "Prediction/Interval": record.interval_um,
            "Prediction/Training Span": record.training_span,
            "Prediction/Outside Inputs": ",".join(record.outside_inputs),
        }
    )
    values.update({f"Health/{k}": v for k, v in health_counters(health).items()})
    for name, axis in record.axes.items():
        for leaf, _, _, attribute in AXIS_LEAVES:
            value = getattr(axis, attribute)
            values[f"Axes/{name}/{leaf}"] = ",".join(value) if isinstance(value, list) else value
    return values


def changed(
    specs: Sequence[MetricSpec], before: Mapping[str, Value], now: Mapping[str, Value]
) -> list[MetricSpec]:
    """The metrics whose value differs from ``before``; the cycle counter always."""
    return [s for s in specs if s.name == CYCLES or before.get(s.name, object()) != now.get(s.name)]
