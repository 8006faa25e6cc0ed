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


def axis_macros(machine: object) -> dict[str, int | None]:
    """Each configured axis's macro variable number (None where the section has none)."""
    found: dict[str, int | None] = {}
    for name, section in _axes_section(machine).items():
        macro = section.get("macro") if isinstance(section, Mapping) else None
        macro = getattr(section, "macro", macro)
        found[str(name)] = int(macro) if isinstance(macro, int) else None
    return found
