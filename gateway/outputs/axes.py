"""The axes of a machine as every output names them.

A machine configured with ``compensation.axes`` compensates several axes from one poll;
its :class:`~gateway.live.record.CycleRecord` carries one
:class:`~gateway.live.record.AxisRecord` per axis. The SCADA server and the Sparkplug
node create their nodes and metrics once at start, before any record, so they take the
axis names (and each axis's macro) from the configuration here: ``compensation.axes`` in
its key order (the order of the writes; the first is the primary axis), and none for
the single-axis form.
"""

from __future__ import annotations

from collections.abc import Mapping


def _axes_section(machine: object) -> Mapping[str, object]:
    compensation = getattr(machine, "compensation", None)
    axes = getattr(compensation, "axes", None)
    return axes if isinstance(axes, Mapping) else {}


def axis_names(machine: object) -> list[str]:
    """The machine's configured axes in order (first = primary); [] for one axis."""
    return [str(name) for name in _axes_section(machine)]


def axis_setting(machine: object, key: str, default: object = None) -> dict[str, object]:
    """Each configured axis's ``key`` (e.g. ``macro``, ``unit``, ``sign``), ``default``
    where its section has none."""
    found: dict[str, object] = {}
    for name, section in _axes_section(machine).items():
        value = section.get(key, default) if isinstance(section, Mapping) else default
        found[str(name)] = getattr(section, key, value)
    return found


def axis_macros(machine: object) -> dict[str, int | None]:
    """Each configured axis's macro variable number (None where the section has none)."""
    return {
        axis: macro if isinstance(macro, int) else None
        for axis, macro in axis_setting(machine, "macro").items()
    }


def axis_cnc_um_per_unit(machine: object) -> dict[str, float]:
    """Each configured axis's µm per unit of the value its macro holds: 1000 × sign for
    mm, sign for µm (the axis's ``unit`` and ``sign``, else the compensation section's)."""
    compensation = getattr(machine, "compensation", None)
    units = axis_setting(machine, "unit", getattr(compensation, "unit", "mm"))
    signs = axis_setting(machine, "sign", getattr(compensation, "sign", 1))
    return {
        axis: (1000.0 if units[axis] == "mm" else 1.0) * (-1.0 if signs[axis] == -1 else 1.0)
        for axis in units
    }
