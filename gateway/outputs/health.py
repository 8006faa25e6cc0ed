"""A machine's health counters and the process's, assembled in one place.

Every reader takes them from :func:`machine_health` (through
:meth:`gateway.wiring.Gateway.health`): the SCADA server's ``Machines/<id>/Health``
nodes (:func:`scalar_counters`), the heartbeat file the container's health check
reads (:class:`gateway.outputs.sinks.Outputs`), the console's overview row and the
Sparkplug devices' ``Health/…`` metrics (:func:`integer_counters`; the node's own are
:func:`gateway_counters`). Each counter is therefore named and computed once, and the
readers cannot disagree.

The mapping, by source (keys are part of the public contracts):

- the machine loop: ``failed_writes``, ``external_changes``, ``link_errors_total``,
  ``sink_failures`` (and ``sink_failures_by_sink``), ``cycles``,
  ``compensation_enabled``, ``model_swaps``, ``model_swaps_refused``;
- its supervisor (:mod:`gateway.process.supervision`): ``loop_restarts``,
  ``last_loop_error``;
- the process-wide store-and-forward path (:mod:`gateway.outputs.influx`):
  ``forwarder_backlog``, ``dropped_points``, ``rejected_points``,
  ``forwarder_restarts`` and, with InfluxDB configured, ``forwarder_connected``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from gateway.outputs.influx import Forwarder
    from gateway.process.supervision import Supervised

#: One machine's health: counters, flags, the last error's text, failures per sink.
Health = dict[str, int | bool | str | dict[str, int] | None]


def loop_counters(loop: Any) -> dict[str, int | bool]:
    """The counters a ``MachineLoop`` keeps (any object with its attributes)."""
    promotions = getattr(loop, "promotions", None)
    return {
        "failed_writes": int(loop.failed_writes),
        "external_changes": int(getattr(loop, "external_changes", 0)),
        "link_errors_total": int(getattr(loop, "link_errors", 0)),
        "sink_failures": int(sum(getattr(loop, "sink_failures", {}).values())),
        "cycles": int(loop.cycles),
        "compensation_enabled": bool(loop.compensation_enabled),
        "model_swaps": int(getattr(promotions, "swaps", 0)),
        "model_swaps_refused": int(getattr(promotions, "refused", 0)),
    }


def supervisor_counters(supervisor: Supervised) -> dict[str, int | str | None]:
    """Restarts of a machine's loop after a failure, and the last failure."""
    return {"loop_restarts": supervisor.restarts, "last_loop_error": supervisor.last_error}


def forwarder_counters(forwarder: Forwarder | None) -> dict[str, int | bool]:
    """Backlog, dropped points and restarts of the store-and-forward path (zeros with
    the local store, which has no backlog)."""
    if forwarder is None:
        return {
            "forwarder_backlog": 0,
            "dropped_points": 0,
            "rejected_points": 0,
            "forwarder_restarts": 0,
        }
    health = forwarder.health()
    return {
        "forwarder_backlog": int(health["buffered"]),
        "dropped_points": int(health["dropped"]),  # the buffer was full: oldest dropped
        "rejected_points": int(health["rejected"]),  # InfluxDB refused them as invalid
        "forwarder_restarts": int(health["restarts"]),
        "forwarder_connected": bool(health["connected"]),
    }


def machine_health(loop: Any, supervisor: Supervised, forwarder: Forwarder | None) -> Health:
    """Every health counter of one machine, plus the process-wide forwarder's."""
    return {
        **loop_counters(loop),
        "sink_failures_by_sink": dict(getattr(loop, "sink_failures", {})),
        **supervisor_counters(supervisor),
        **forwarder_counters(forwarder),
    }


def gateway_counters(forwarder: Forwarder | None) -> dict[str, int]:
    """The process's own integer counters, not any one machine's (the Sparkplug node's
    ``Health/…`` metrics of NBIRTH and NDATA): the forwarder's, which every machine's
    health also repeats."""
    return integer_counters(forwarder_counters(forwarder))


def scalar_counters(health: Mapping[str, Any]) -> dict[str, int | float | str | bool]:
    """What the SCADA server shows: every single value (numbers, flags, texts)."""
    return {k: v for k, v in health.items() if isinstance(v, int | float | str | bool)}


def integer_counters(health: Mapping[str, Any]) -> dict[str, int]:
    """The integer counters (flags, texts and nested maps left out): the console's
    overview row and the Sparkplug ``Health/…`` metrics."""
    return {k: int(v) for k, v in health.items() if isinstance(v, int) and not isinstance(v, bool)}
