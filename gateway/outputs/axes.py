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

from typing import Literal

from gateway.config import AxisSection, MachineSection
from gateway.limits import UM_PER_UNIT


def _axes(machine: MachineSection) -> dict[str, AxisSection]:
    return dict(machine.compensation.axes or {})


def axis_names(machine: MachineSection) -> list[str]:
    """The machine's configured axes in order (first = primary); [] for one axis."""
    return list(_axes(machine))


def axis_macros(machine: MachineSection) -> dict[str, int]:
    """Each configured axis's macro variable number."""
    return {name: axis.macro for name, axis in _axes(machine).items()}


def cnc_um_per_unit(unit: Literal["mm", "um"], sign: int) -> float:
    """µm of compensation per unit of the value a macro holds (its unit and sign)."""
    return UM_PER_UNIT[unit] * sign


def axis_cnc_um_per_unit(machine: MachineSection) -> dict[str, float]:
    """Each configured axis's µm per unit of the value its macro holds."""
    return {name: cnc_um_per_unit(axis.unit, axis.sign) for name, axis in _axes(machine).items()}
