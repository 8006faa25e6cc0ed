"""The edge node from the ``sparkplug`` section of the configuration."""

from __future__ import annotations

import socket
from collections.abc import Callable, Mapping
from typing import Any

from gateway.config import GatewayConfig
from gateway.outputs.axes import axis_names
from gateway.outputs.disk_buffer import PointBuffer
from gateway.sparkplug.commands import Actions, Allowed, CommandHandler
from gateway.sparkplug.metrics import health_counters
from gateway.sparkplug.mqtt import MqttSettings
from gateway.sparkplug.node import EdgeNode, NodeSettings


def build_node(
    config: GatewayConfig,
    health: Callable[[str], Mapping[str, Any]],
    actions: Actions,
    gateway_health: Callable[[], Mapping[str, int]] = dict,
) -> EdgeNode:
    """An edge node for ``config.sparkplug`` (which must be set); its buffer opened.
    ``health`` gives a machine's counters (its DBIRTH/DDATA), ``gateway_health`` the
    process's own (the node's NBIRTH/NDATA)."""
    section = config.sparkplug
    assert section is not None
    first = config.machines[0].id
    settings = NodeSettings(
        group_id=section.group_id,
        edge_node_id=section.edge_node_id,
        primary_host_id=section.primary_host_id,
        machines={m.id: tuple(m.sensor_names) for m in config.machines},
        health_keys=tuple(health_counters(health(first))),
        state_dir=config.state_dir,
        startup_delay_max_s=section.startup_delay_max_s,
        reconnect_max_s=section.reconnect_max_s,
        axes={m.id: tuple(axis_names(m)) for m in config.machines if axis_names(m)},
    )
    mqtt = MqttSettings(
        brokers=tuple(section.brokers),
        client_id=section.client_id or f"{section.edge_node_id}-{socket.gethostname()}",
        username=section.username,
        password=section.password(),
        ca_file=section.ca_file,
        cert_file=section.cert_file,
        key_file=section.key_file,
        qos=section.qos,
        keepalive_s=section.keepalive_s,
    )
    buffer = PointBuffer(section.buffer_path, section.buffer_max_points)
    c = section.commands
    allowed = Allowed(c.set_compensation, c.promote_proposal, c.rollback_models)
    commands = CommandHandler(allowed, actions)
    return EdgeNode(settings, mqtt, buffer, commands, health, gateway_health)
