"""Commands from the Sparkplug host (NCMD, DCMD): checked, then acted on or refused.

A command is refused, logged and counted, never acted on, when its payload does not
decode, a metric names an unknown alias or name, its datatype is not the metric's,
the action is not allowed in the configuration (``sparkplug.commands``, all off by
default), or it replays a command already taken (same payload timestamp and seq).
Allowed actions call the same gateway functions as the SCADA OPC UA methods, so the
same safety rules apply (a promotion is checked against the machine's models).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from gateway.sparkplug import sparkplug_b_pb2 as pb
from gateway.sparkplug.metrics import ENABLED, PROMOTE, REBIRTH, ROLLBACK, WRITABLE
from gateway.sparkplug.payload import DATATYPE_NAMES, MetricSpec, decode, value_of

log = logging.getLogger(__name__)

#: How many accepted (timestamp, seq) pairs are remembered to refuse replays.
REPLAY_MEMORY = 1024


@dataclass(frozen=True)
class Allowed:
    """Which device commands the configuration allows (each off unless named)."""

    set_compensation: bool = False
    promote_proposal: bool = False
    rollback_models: bool = False


@dataclass(frozen=True)
class Actions:
    """The gateway's own functions a command may call (those the SCADA methods call)."""

    set_enabled: Callable[[str, bool], None]
    promote: Callable[[str, str], str]
    rollback: Callable[[str], str]
    rebirth: Callable[[], None]


class CommandRefusedError(ValueError):
    """A command that is not acted on; the message says why."""


@dataclass
class CommandHandler:
    allowed: Allowed
    actions: Actions
    accepted: int = 0
    refused: int = 0
    _seen: deque[tuple[int, int | None]] = field(
        default_factory=lambda: deque(maxlen=REPLAY_MEMORY)
    )

    def handle(self, data: bytes, specs: Sequence[MetricSpec], device: str | None) -> bool:
        """Check and run one command; True when acted on (refusals are logged, counted)."""
        where = "NCMD" if device is None else f"DCMD to {device}"
        try:
            steps = self._checked(data, specs, device)
        except CommandRefusedError as exc:
            self.refused += 1
            log.warning("Sparkplug %s refused: %s", where, exc)
            return False
        for name, run in steps:
            try:
                outcome = run()
            except (KeyError, ValueError) as exc:  # the gateway refused it (the SCADA rules)
                self.refused += 1
                log.warning("Sparkplug %s %s refused by the gateway: %s", where, name, exc)
                return False
            self.accepted += 1
            log.warning("Sparkplug %s %s done%s", where, name, f": {outcome}" if outcome else "")
        return True

    def _checked(
        self, data: bytes, specs: Sequence[MetricSpec], device: str | None
    ) -> list[tuple[str, Callable[[], object]]]:
        try:
            payload = decode(data)
        except ValueError as exc:
            raise CommandRefusedError(str(exc)) from None
        key = (payload.timestamp, payload.seq if payload.HasField("seq") else None)
        if not payload.HasField("timestamp"):
            raise CommandRefusedError("no payload timestamp (needed to refuse replays)")
        if key in self._seen:
            raise CommandRefusedError(f"replayed command (timestamp {key[0]}, seq {key[1]})")
        if not payload.metrics:
            raise CommandRefusedError("no metric")
        by_alias = {s.alias: s for s in specs if s.alias is not None}
        by_name = {s.name: s for s in specs}
        steps = [self._step(m, by_alias, by_name, device) for m in payload.metrics]
        self._seen.append(key)
        return steps

    def _step(
        self,
        metric: pb.Payload.Metric,
        by_alias: Mapping[int, MetricSpec],
        by_name: Mapping[str, MetricSpec],
        device: str | None,
    ) -> tuple[str, Callable[[], object]]:
        spec = _spec_of(metric, by_alias, by_name)
        kind = WRITABLE.get(spec.name)
        if kind is None:
            raise CommandRefusedError(f"{spec.name} is read-only; {_writable(by_name)}")
        if metric.HasField("datatype") and metric.datatype != spec.datatype:
            raise CommandRefusedError(
                f"{spec.name}: datatype {_type_name(metric.datatype)} where "
                f"{_type_name(spec.datatype)} is expected"
            )
        value = value_of(metric)
        if not isinstance(value, kind) or not isinstance(value, bool | str):
            wanted = _type_name(spec.datatype)
            raise CommandRefusedError(f"{spec.name}: a {wanted} value expected, got {value!r}")
        return spec.name, self._action(spec.name, value, device)

    def _action(self, name: str, value: bool | str, device: str | None) -> Callable[[], object]:
        a, allowed = self.actions, self.allowed
        if device is None:
            if name == REBIRTH and value is True:
                return a.rebirth
            raise CommandRefusedError(f"{name}={value!r} is not a node command")
        if name == ENABLED and allowed.set_compensation:
            return lambda: a.set_enabled(device, bool(value))
        if name == PROMOTE and allowed.promote_proposal and value:
            return lambda: a.promote(device, str(value))
        if name == ROLLBACK and allowed.rollback_models and value is True:
            return lambda: a.rollback(device)
        raise CommandRefusedError(f"{name}={value!r} is not allowed by sparkplug.commands")


def _type_name(datatype: int) -> str:
    return DATATYPE_NAMES.get(datatype, f"datatype {datatype}")


def _writable(by_name: Mapping[str, MetricSpec]) -> str:
    """The metrics a host may write here, with their datatypes (for a refusal's text)."""
    names = [f"{s.name} ({_type_name(s.datatype)})" for s in by_name.values() if s.name in WRITABLE]
    return "the writable metrics are " + ", ".join(names)


def _spec_of(
    metric: pb.Payload.Metric, by_alias: Mapping[int, MetricSpec], by_name: Mapping[str, MetricSpec]
) -> MetricSpec:
    if metric.HasField("alias"):
        spec = by_alias.get(metric.alias)
        if spec is None:
            raise CommandRefusedError(f"unknown alias {metric.alias}")
        return spec
    spec = by_name.get(metric.name)
    if spec is None:
        raise CommandRefusedError(f"unknown metric {metric.name!r}")
    return spec
