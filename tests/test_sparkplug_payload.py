"""Sparkplug B payloads, topics, STATE and command checks (pure; the wire is in
test_sparkplug_host)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from gateway.outputs.disk_buffer import PointBuffer
from gateway.sparkplug import regenerate, topics
from gateway.sparkplug.commands import Actions, Allowed, CommandHandler
from gateway.sparkplug.metrics import ENABLED, NODE_METRICS, device_specs
from gateway.sparkplug.mqtt import MqttSettings
from gateway.sparkplug.node import EdgeNode, NodeSettings, state_of
from gateway.sparkplug.payload import (
    BOOLEAN,
    DOUBLE,
    INT64,
    STRING,
    Payload,
    decode,
    encode,
    value_of,
)


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
    rebirth = Payload(timestamp=13, seq=2)
    rebirth.metrics.add(name="Node Control/Rebirth", datatype=BOOLEAN, boolean_value=True)
    data = rebirth.SerializeToString()
    assert handler.handle(data, NODE_METRICS, None) and calls[-1] == ("rebirth", True)
    applied = next(s.alias for s in specs if s.name == "Compensation/Applied")
    assert not handler.handle(_command(applied, DOUBLE, 14, double_value=1000.0), specs, "m1")
    assert calls[-1] == ("rebirth", True) and handler.refused == 5


def test_state_payload_must_be_online_bool_and_timestamp_int() -> None:
    assert state_of(b'{"online": false, "timestamp": 1700000000000}') == (False, 1700000000000)
    bad = {
        b'{"online": "yes"}': "online is 'yes', not a boolean",
        b'{"online": true}': "timestamp is None, not an integer",
        b'{"online": true, "timestamp": true}': "timestamp is True, not an integer",
        b'{"online": true, "timestamp": "1000"}': "timestamp is '1000', not an integer",
        b"[true, 1000]": "expected JSON",
        b"ONLINE": "not JSON",
    }
    for data, reason in bad.items():
        with pytest.raises(ValueError, match=re.escape(reason)):
            state_of(data)


def test_ndeath_names_its_bdseq_and_rebirth_goes_by_name(tmp_path: Path) -> None:
    settings = NodeSettings("g", "n", "h", {"m1": ("T1",)}, ("cycles",), tmp_path)
    (tmp_path / "sparkplug-bdseq.json").write_text('{"bdSeq": 6}')
    actions = Actions(lambda m, on: None, lambda m, p: "", lambda m: "", lambda: None)
    buffer = PointBuffer(tmp_path / "buffer.sqlite", 10)
    try:
        node = EdgeNode(settings, MqttSettings(("mqtt://x",), "c"), buffer,
                        CommandHandler(Allowed(), actions), lambda m: {})  # fmt: skip
        death = decode(node.death_payload())
    finally:
        buffer.close()
    assert not death.HasField("seq") and len(death.metrics) == 1
    bd_seq = death.metrics[0]
    assert (bd_seq.name, bd_seq.datatype, bd_seq.long_value) == ("bdSeq", INT64, 7)
    assert [s.alias for s in node.node_specs if s.name == "Node Control/Rebirth"] == [None]
    birth = decode(encode(node.node_specs, {"Node Control/Rebirth": False}, seq=0,
                          timestamp_ms=1, birth=True))  # fmt: skip
    rebirth = next(m for m in birth.metrics if m.name == "Node Control/Rebirth")
    assert not rebirth.HasField("alias") and rebirth.datatype == BOOLEAN
