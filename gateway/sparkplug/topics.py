"""Sparkplug B topic names (spBv1.0): what the edge node publishes and listens to."""

from __future__ import annotations

from dataclasses import dataclass

NAMESPACE = "spBv1.0"
FORBIDDEN = set("+#/")


def check_id(value: str, what: str) -> str:
    """A group, edge node, device or host id: non-empty, no MQTT wildcard or level separator."""
    if not value or FORBIDDEN & set(value):
        raise ValueError(f"{what} '{value}' must be non-empty and contain none of + # /")
    return value


def node_topic(group: str, kind: str, node: str) -> str:
    """``spBv1.0/<group>/<NBIRTH|NDATA|NDEATH|NCMD>/<node>``."""
    return f"{NAMESPACE}/{group}/{kind}/{node}"


def device_topic(group: str, kind: str, node: str, device: str) -> str:
    """``spBv1.0/<group>/<DBIRTH|DDATA|DDEATH|DCMD>/<node>/<device>``."""
    return f"{NAMESPACE}/{group}/{kind}/{node}/{device}"


def state_topic(host: str) -> str:
    """The primary host's retained STATE topic (Sparkplug 3.0)."""
    return f"{NAMESPACE}/STATE/{host}"


@dataclass(frozen=True)
class Incoming:
    """What a received topic addresses: ``kind`` NCMD, DCMD or STATE, and the device."""

    kind: str
    device: str | None = None
    host: str | None = None


def parse(topic: str, group: str, node: str) -> Incoming | None:
    """The command or STATE a topic addresses to this node; None for anything else."""
    parts = topic.split("/")
    if len(parts) == 3 and parts[:2] == [NAMESPACE, "STATE"]:
        return Incoming("STATE", host=parts[2])
    if len(parts) < 4 or parts[0] != NAMESPACE or parts[1] != group or parts[3] != node:
        return None
    if parts[2] == "NCMD" and len(parts) == 4:
        return Incoming("NCMD")
    if parts[2] == "DCMD" and len(parts) == 5:
        return Incoming("DCMD", device=parts[4])
    return None
