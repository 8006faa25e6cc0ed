"""The axes of a machine as every output names them.

A machine configured with ``compensation.axes`` compensates several axes from one poll;
its :class:`~gateway.live.record.CycleRecord` carries one
:class:`~gateway.live.record.AxisRecord` per axis. The SCADA server and the Sparkplug
node create their nodes and metrics once at start, before any record, so they take the
axis names (and each axis's macro) from the configuration here: ``compensation.axes`` in
its key order (the order of the writes; the first is the primary axis), and none for
the single-axis form, whose outputs are those of one axis as they always were.
"""

from __future__ import annotations

from gateway.config import AxisSection, MachineSection


def _axes(machine: MachineSection) -> dict[str, AxisSection]:
    return dict(machine.compensation.axes or {})


def axis_names(machine: MachineSection) -> list[str]:
    """The machine's configured axes in order (first = primary); [] for one axis."""
    return list(_axes(machine))


def axis_macros(machine: MachineSection) -> dict[str, int]:
    """Each configured axis's macro variable number."""
    return {name: axis.macro for name, axis in _axes(machine).items()}


def axis_cnc_um_per_unit(machine: MachineSection) -> dict[str, float]:
    """Each configured axis's µm per unit of the value its macro holds: 1000 × sign for
    mm, sign for µm."""
    return {
        name: (1000.0 if axis.unit == "mm" else 1.0) * float(axis.sign)
        for name, axis in _axes(machine).items()
    }
