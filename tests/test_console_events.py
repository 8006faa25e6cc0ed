"""The console's event table from what the gateway logs: a sensor that breaks without a
value (an open circuit) is listed when it broke, and again when it recovered.

Real parts: the records become points as the gateway makes them, go into the local
SQLite store and are read back by the console's reader (gateway.web.series).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gateway.live.record import CycleRecord
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import points_from_record
from gateway.web.series import events, read_machine
from tests.test_timeseries import EPOCH_S, make_records

OPEN = "transmitter fault code 1 (open circuit)"
BROKEN = range(20, 26)  # cycles with T3 open circuit: no value at all
RECOVERING = range(26, 29)  # values again, held bad for three good checks


def _with_a_break(records: list[CycleRecord]) -> list[CycleRecord]:
    for i in BROKEN:
        records[i].temperatures_C["T3"] = None
        records[i].quality["T3"] = "bad"
        records[i].quality_reasons["T3"] = OPEN
    for i in RECOVERING:
        records[i].quality["T3"] = "bad"
        records[i].quality_reasons["T3"] = "recovering"
    return records


def test_an_open_circuit_is_listed_when_it_broke_and_when_it_recovered(tmp_path: Path) -> None:
    records = _with_a_break(make_records("m1", 40))
    path = tmp_path / "points.sqlite"
    with LocalStore(path) as store:
        store.write([p for r in records for p in points_from_record(r, EPOCH_S)])
    data = read_machine(("local", str(path)), "m1", EPOCH_S, EPOCH_S + 40, 1000.0)

    flags = [(t - EPOCH_S, text) for t, kind, text in events(data) if kind == "sensor flag"]
    assert flags == [(29.0, "T3: bad → good"), (20.0, "T3: good → bad")]
    # the broken cycles are gaps in T3's curve, never a value
    t_s, value_C = data.temperatures_C["T3"]
    broken = (t_s >= EPOCH_S + BROKEN.start) & (t_s < EPOCH_S + BROKEN.stop)
    assert broken.sum() == len(BROKEN) and np.isnan(value_C[broken]).all()
