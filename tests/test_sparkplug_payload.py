"""Sparkplug B payloads, topics and command checks (pure; the wire is in test_sparkplug_host)."""

from __future__ import annotations

import pytest

from gateway.sparkplug import regenerate, topics
from gateway.sparkplug.commands import Actions, Allowed, CommandHandler
from gateway.sparkplug.metrics import ENABLED, NODE_METRICS, device_specs
from gateway.sparkplug.payload import BOOLEAN, DOUBLE, STRING, Payload, decode, encode, value_of


def test_committed_pb2_equals_what_protoc_makes_of_the_proto() -> None:
    for path, text in regenerate.generate().items():
        assert path.read_text(encoding="utf-8") == text, path


def test_birth_carries_name_datatype_unit_alias_and_data_only_the_alias() -> None:
    specs = device_specs(0, ["T1"], ["cycles"])
    values = {"Temperature/T1": 21.5, "Spindle/Speed": None, ENABLED: True, "Regime": "warm"}
    birth = decode(encode(specs, values, seq=3, timestamp_ms=1000, birth=True))
    by_name = {m.name: m for m in birth.metrics}
    t1 = by_name["Temperature/T1"]
    assert (t1.datatype, t1.double_value, t1.alias) == (DOUBLE, 21.5, 1000)
    assert list(t1.properties.keys) == ["engUnit"] and t1.properties.values[0].string_value == "°C"
    assert by_name["Spindle/Speed"].is_null and value_of(by_name["Spindle/Speed"]) is None
    assert by_name[ENABLED].datatype == BOOLEAN and value_of(by_name[ENABLED]) is True
    assert by_name["Regime"].datatype == STRING and birth.seq == 3
    data = decode(encode(specs[:1], values, seq=4, timestamp_ms=2000, historical=True))
    assert not data.metrics[0].name and data.metrics[0].alias == 1000
    assert data.metrics[0].is_historical


def test_topics_of_this_node_only() -> None:
    assert topics.parse("spBv1.0/g/DCMD/n/m1", "g", "n") == topics.Incoming("DCMD", "m1")
    assert topics.parse("spBv1.0/g/NCMD/n", "g", "n") == topics.Incoming("NCMD")
    assert topics.parse("spBv1.0/STATE/h", "g", "n") == topics.Incoming("STATE", host="h")
    assert topics.parse("spBv1.0/g/DCMD/other/m1", "g", "n") is None
    with pytest.raises(ValueError, match="none of"):
        topics.check_id("a/b", "group_id")


def _command(alias: int, datatype: int, timestamp: int, **value: object) -> bytes:
    payload = Payload(timestamp=timestamp, seq=1)
    metric = payload.metrics.add(alias=alias, datatype=datatype)
    for field, v in value.items():
        setattr(metric, field, v)
    return payload.SerializeToString()


def test_commands_act_only_when_allowed_well_typed_known_and_new() -> None:
    calls: list[tuple[str, bool]] = []
    actions = Actions(
        set_enabled=lambda m, on: calls.append((m, on)),
        promote=lambda m, p: "",
        rollback=lambda m: "",
        rebirth=lambda: calls.append(("rebirth", True)),
    )
    specs = device_specs(0, ["T1"], [])
    alias = next(s.alias for s in specs if s.name == ENABLED)
    off = _command(alias, BOOLEAN, 10, boolean_value=False)

    closed = CommandHandler(Allowed(), actions)
    assert not closed.handle(off, specs, "m1") and calls == [] and closed.refused == 1

    handler = CommandHandler(Allowed(set_compensation=True), actions)
    assert handler.handle(off, specs, "m1") and calls == [("m1", False)]
    assert not handler.handle(off, specs, "m1")  # replayed
    assert not handler.handle(_command(alias, STRING, 11, string_value="no"), specs, "m1")
    assert not handler.handle(_command(99999, BOOLEAN, 12, boolean_value=True), specs, "m1")
    assert not handler.handle(b"\xff\xff\x0a\x01", specs, "m1")
    assert calls == [("m1", False)] and handler.refused == 4
    rebirth = _command(NODE_METRICS[1].alias, BOOLEAN, 13, boolean_value=True)
    assert handler.handle(rebirth, NODE_METRICS, None) and calls[-1] == ("rebirth", True)
