"""One standard OPC UA address space per test process, copied into every asyncua server.

asyncua fills each new server's standard address space (some 6 000 nodes) from its
generated code: about a second of CPU per server, and the suite starts dozens of
servers in-process (the simulated CNCs, their restarts, the gateway's SCADA). The
fill is the same every time, so the first one is kept, taken right after the fill
and before the server adds or changes anything, and each later server gets a copy:
its own node records, attribute records and references, and its own copy of every
list value (asyncua's ``register_namespace`` appends to the value it read). The
values themselves are immutable once stored: a write replaces them.

Only the tests use this (:func:`install`, from tests/conftest.py); the servers are
otherwise asyncua's own, and a fill that already carries callbacks is not kept.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AttributeValue, NodeData
from asyncua.server.internal_server import InternalServer

_fill = InternalServer.load_standard_address_space
_template: list[dict[ua.NodeId, NodeData]] = []


def _own(value: ua.DataValue | None) -> ua.DataValue | None:
    """``value``, with a copy of its list, if it holds one (lists are changed in place)."""
    if value is None or value.Value is None or not isinstance(value.Value.Value, list):
        return value
    return dataclasses.replace(
        value, Value=dataclasses.replace(value.Value, Value=list(value.Value.Value))
    )


def _copy(nodes: dict[ua.NodeId, NodeData]) -> dict[ua.NodeId, NodeData]:
    copied: dict[ua.NodeId, NodeData] = {}
    for nodeid, node in nodes.items():
        twin = NodeData(nodeid)
        for attribute, record in node.attributes.items():
            twin.attributes[attribute] = AttributeValue(_own(record.value))
        twin.references = [copy.copy(reference) for reference in node.references]
        copied[nodeid] = twin
    return copied


def _plain(nodes: dict[ua.NodeId, NodeData]) -> bool:
    """No callbacks anywhere: the fill is data only, so a copy of it is a fill."""
    return all(
        node.call is None
        and all(
            a.value_callback is None and a.value_setter is None and not a.datachange_callbacks
            for a in node.attributes.values()
        )
        for node in nodes.values()
    )


async def _load(self: InternalServer, shelf_file: Path | None = None) -> Any:
    if shelf_file is not None:
        return await _fill(self, shelf_file)
    if _template:
        self.aspace._nodes = _copy(_template[0])
        return None
    await _fill(self)
    if _plain(self.aspace._nodes):
        _template.append(_copy(self.aspace._nodes))
    return None


def install() -> None:
    """Every asyncua server of this process starts from the kept standard address space."""
    InternalServer.load_standard_address_space = _load  # type: ignore[method-assign]
