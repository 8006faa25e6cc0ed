"""Augmented models stepped sample by sample give the batch predictions, and carry their state.

Documents come from ``analyze --store`` on the real fl_thermal.csv recording and
on simulator data with hidden effects; effect kinds the data do not provoke are
added by hand to real documents (checksum recomputed), and every document is
streamed row by row and compared with :func:`models.analysis.augmented.predict`.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gateway.live.bank.lag_state import EffectStates
from gateway.live.bank.model_bank import BankedAugmented, ModelBank
from models.analysis import augmented
from models.data.dataset import load_runs
from models.data.features import Prepared, prepare
from models.data.references import first_rows
from models.online.streaming import StreamingAugmented
from models.store import StoreError
from simulator.params import load_params
from simulator.programs import load_programs
from simulator.record import DEFAULT_PROGRAMS, record, write_recording
from tests.cli import ROOT, gateway_in_process

FL_THERMAL = ROOT / "data" / "fl_thermal.csv"
HIDDEN = ["thermal_lag", "speed_direct", "ambient", "drift"]
ALL_KINDS = {"thermal_lag", "speed_direct", "unsensed_heat", "ambient", "drift", "unused_sensor"}
TOLERANCE_UM = 1e-6


def analyzed(data: Path, store: Path, *options: str) -> dict[str, Any]:
    """``analyze --store`` as a user runs it; the augmented document it saved."""
    done = gateway_in_process("analyze", data, "--model", "mlr", *options, "--store", store)
    assert done.returncode == 0, done.stderr
    (path,) = (store / augmented.FOLDER).glob("*.json")
    return augmented.load(path)


def by_hand(document: dict[str, Any], extra: list[dict[str, Any]], store: Path) -> dict[str, Any]:
    """``document`` with more effects (and a coefficient per term), saved and loaded again."""
    widths = {"thermal_lag": len(document["effect_sensors"]), "speed_direct": 2}
    widths["unsensed_heat"] = 2
    changed = copy.deepcopy(document)
    del changed["sha256"]
    coefficients = changed["coefficients"]["all_um_per_unit"]
    rng = np.random.default_rng(7)
    for effect in extra:
        terms = widths.get(effect["effect"], 1)
        changed["effects"].append({**effect, "terms": terms})
        coefficients.extend(rng.uniform(-2.0, 2.0, terms).tolist())
    changed["model_id"] += "-by-hand"
    changed["sha256"] = augmented._checksum(changed)
    return augmented.load(augmented.save(changed, store))


@dataclass(frozen=True)
class Row:
    time_s: float
    rises_C: dict[str, float]
    speed_rpm: float
    ambient_rise_C: float | None
    starts_recording: bool
    starts_run: bool


def rows_of(prepared: Prepared, sensors: tuple[str, ...]) -> Iterator[Row]:
    """The file's samples as the gateway would see them: rises above each recording's start."""
    data, recording = prepared.data, prepared.plan.recording
    columns = {name: prepared.plan.rises(data.numeric[name]) for name in sensors}
    ambient = None if data.ambient_C is None else prepared.plan.rises(data.ambient_C)
    recording_first, run_first = first_rows(recording), first_rows(data.run_index)
    for k in range(data.n_samples):
        yield Row(
            time_s=float(data.time_s[k]),
            rises_C={name: float(values[k]) for name, values in columns.items()},
            speed_rpm=float(data.speed_rpm[k]),
            ambient_rise_C=None if ambient is None else float(ambient[k]),
            starts_recording=bool(recording_first[k] == k),
            starts_run=bool(run_first[k] == k),
        )


def streamed(document: dict[str, Any], prepared: Prepared) -> np.ndarray:
    """Every row stepped in order; each recording starts a fresh stream at its reference
    (speed from 0 r/min, as the runtime takes it)."""
    out = np.empty(prepared.data.n_samples)
    sensors = StreamingAugmented(document).sensors
    stream = None
    for k, row in enumerate(rows_of(prepared, sensors)):
        if stream is None or row.starts_recording:
            stream = StreamingAugmented(document)
        if row.starts_run:
            stream.start_run(row.time_s)
        value = stream.step(row.time_s, row.rises_C, row.speed_rpm, row.ambient_rise_C)
        assert value is not None
        out[k] = value
    return out


@pytest.fixture(scope="module")
def fl_prepared() -> Prepared:
    return prepare(load_runs(FL_THERMAL, target="ch1_um"))


@pytest.fixture(scope="module")
def sim_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("sim") / "hidden-effects.csv"
    programs = load_programs()
    recording = record(load_params(), [programs[p] for p in DEFAULT_PROGRAMS], HIDDEN, seed=1)
    write_recording(path, recording)
    return path


@pytest.fixture(scope="module")
def sim_prepared(sim_csv: Path) -> Prepared:
    return prepare(load_runs(sim_csv))


@pytest.fixture(scope="module")
def documents(tmp_path_factory: pytest.TempPathFactory, sim_csv: Path) -> dict[str, dict]:
    """Stored by ``analyze``, and the same with the kinds the data left out added by hand."""
    folder = tmp_path_factory.mktemp("stores")
    fl = analyzed(FL_THERMAL, folder / "fl", "--target", "ch1_um")
    fl_few = analyzed(FL_THERMAL, folder / "fl-few", "--target", "ch1_um", "--sensors", "T1,T5,T9")
    sim = analyzed(sim_csv, folder / "sim")
    fl_by_hand = by_hand(
        fl_few,
        [
            {"effect": "thermal_lag", "params": {"tau_s": 600.0}},
            {"effect": "thermal_lag", "params": {"tau_s": 28800.0}},
            {"effect": "unsensed_heat", "params": {"tau_s": 1200.0}},
            {"effect": "speed_direct", "params": {}},
            {"effect": "drift", "params": {"origin": "run"}},
            {"effect": "drift", "params": {"origin": "recording"}},
            {"effect": "unused_sensor", "params": {"sensor": "T16"}},
        ],
        folder / "by-hand",
    )
    sim_by_hand = by_hand(
        sim,
        [
            {"effect": "ambient", "params": {"tau_s": 0.0}},
            {"effect": "ambient", "params": {"tau_s": 900.0}},
            {"effect": "unsensed_heat", "params": {"tau_s": 600.0}},
        ],
        folder / "by-hand",
    )
    return {"fl": fl, "fl-by-hand": fl_by_hand, "sim": sim, "sim-by-hand": sim_by_hand}


def prepared_for(name: str, request: pytest.FixtureRequest) -> Prepared:
    return request.getfixturevalue("fl_prepared" if name.startswith("fl") else "sim_prepared")


def test_fl_thermal_stored_model_streams_like_batch(
    documents: dict[str, dict], fl_prepared: Prepared
) -> None:
    document = documents["fl"]
    assert document["effects"], "analyze found nothing to add on fl_thermal ch1_um"
    batch = augmented.predict(document, fl_prepared)
    difference_um = np.max(np.abs(streamed(document, fl_prepared) - batch))
    assert difference_um < TOLERANCE_UM


@pytest.mark.parametrize("name", ["fl-by-hand", "sim", "sim-by-hand"])
def test_every_effect_kind_streams_like_batch(
    documents: dict[str, dict], name: str, request: pytest.FixtureRequest
) -> None:
    document, prepared = documents[name], prepared_for(name, request)
    batch = augmented.predict(document, prepared)
    assert np.max(np.abs(streamed(document, prepared) - batch)) < TOLERANCE_UM


def test_the_documents_cover_every_kind_and_parameter(documents: dict[str, dict]) -> None:
    effects = [e for d in documents.values() for e in d["effects"]]
    assert {e["effect"] for e in effects} == ALL_KINDS
    assert {"thermal_lag", "speed_direct", "ambient", "drift"} <= {
        e["effect"] for e in documents["sim"]["effects"]
    }  # found in the data, not added by hand
    assert {0.0, 900.0} <= {e["params"]["tau_s"] for e in effects if e["effect"] == "ambient"}
    origins = {e["params"]["origin"] for e in effects if e["effect"] == "drift"}
    assert origins == {"run", "recording"}


def test_needed_inputs_are_exposed(documents: dict[str, dict]) -> None:
    document = documents["fl-by-hand"]
    stream = StreamingAugmented(document)
    assert stream.sensors == ("T1", "T5", "T9", "T16")
    assert stream.uses_speed and not stream.uses_ambient
    sim = StreamingAugmented(documents["sim"])
    assert sim.sensors == tuple(f"T{i}" for i in range(1, 10))
    assert sim.uses_speed and sim.uses_ambient


def test_exported_state_continues_the_stream(
    documents: dict[str, dict], fl_prepared: Prepared
) -> None:
    document = documents["fl-by-hand"]
    rows = list(rows_of(fl_prepared, StreamingAugmented(document).sensors))
    middle = len(rows) // 2
    original = StreamingAugmented(document)
    for row in rows[:middle]:
        if row.starts_run:
            original.start_run(row.time_s)
        original.step(row.time_s, row.rises_C, row.speed_rpm)
    saved = json.loads(json.dumps(original.export_state()))  # as a restarted gateway reads it
    assert all(isinstance(v, float) for v in saved.values())
    restarted = StreamingAugmented(document)
    restarted.import_state(saved)
    batch = augmented.predict(document, fl_prepared)
    for k, row in enumerate(rows[middle:], start=middle):
        for stream in (original, restarted):
            if row.starts_run:
                stream.start_run(row.time_s)
        expected = original.step(row.time_s, row.rises_C, row.speed_rpm)
        assert restarted.step(row.time_s, row.rises_C, row.speed_rpm) == expected
        assert expected == pytest.approx(batch[k], abs=TOLERANCE_UM)
    with pytest.raises(ValueError, match="does not fit"):
        StreamingAugmented(documents["sim"]).import_state(saved)
    # A state saved before the lags kept their last input loads, and saves as it loaded.
    older = {k: v for k, v in saved.items() if not k.endswith(".input")}
    assert len(older) < len(saved)
    reloaded = StreamingAugmented(document)
    reloaded.import_state(older)
    assert reloaded.export_state() == older
    with pytest.raises(ValueError, match="does not fit"):
        reloaded.import_state(older | {next(k for k in saved if k.endswith(".input")): 0.0})


def test_missing_input_returns_none_and_the_next_sample_spans_the_gap(
    documents: dict[str, dict], sim_prepared: Prepared
) -> None:
    document = documents["sim-by-hand"]
    stream = StreamingAugmented(document)
    first_run = list(rows_of(sim_prepared, stream.sensors))[:200]
    stream = StreamingAugmented(document, speed_ref_rpm=first_run[0].speed_rpm)
    gapless = StreamingAugmented(document, speed_ref_rpm=first_run[0].speed_rpm)
    gap = range(80, 95)
    for k, row in enumerate(first_run):
        if k in gap:
            before = stream.export_state()
            no_t3 = {s: v for s, v in row.rises_C.items() if s != "T3"}
            assert stream.step(row.time_s, no_t3, row.speed_rpm, row.ambient_rise_C) is None
            assert stream.step(row.time_s, row.rises_C, None, row.ambient_rise_C) is None
            assert stream.step(row.time_s, row.rises_C, row.speed_rpm, None) is None
            nan_t3 = row.rises_C | {"T3": float("nan")}
            assert stream.step(row.time_s, nan_t3, row.speed_rpm, row.ambient_rise_C) is None
            assert stream.export_state() == before
            continue
        value = stream.step(row.time_s, row.rises_C, row.speed_rpm, row.ambient_rise_C)
        expected = gapless.step(row.time_s, row.rises_C, row.speed_rpm, row.ambient_rise_C)
        assert value == expected
    with pytest.raises(ValueError, match="time went back"):
        stream.step(0.0, first_run[0].rises_C, 0.0, 0.0)


def test_a_document_the_stream_cannot_run_is_refused(documents: dict[str, dict]) -> None:
    unknown = copy.deepcopy(documents["sim"])
    unknown["effects"].append({"effect": "humidity", "params": {}, "terms": 1})
    with pytest.raises(StoreError, match="unknown effect 'humidity'"):
        StreamingAugmented(unknown)
    short = copy.deepcopy(documents["sim"])
    short["coefficients"]["all_um_per_unit"].pop()
    with pytest.raises(StoreError, match="coefficients stored"):
        StreamingAugmented(short)


def test_bank_loads_augmented_models_with_their_needed_sensors(
    tmp_path: Path, documents: dict[str, dict]
) -> None:
    augmented.save(documents["sim"], tmp_path / "sim")
    bank = ModelBank.from_store(tmp_path / "sim", ambient_sensor="ambient")
    sim = bank.get(documents["sim"]["model_id"])
    assert isinstance(sim, BankedAugmented)
    assert sim.sensors == {f"T{i}" for i in range(1, 10)} | {"ambient"}
    assert sim.ambient_sensor == "ambient"
    assert sim.regime is None
    assert sim.held_out_rmse_um == documents["sim"]["provenance"]["after"]["rmse_um"]
    machine = {f"T{i}" for i in range(1, 17)} | {"ambient"}
    bank.check_sensors(machine)
    with pytest.raises(ValueError, match=r"needs sensor\(s\) \['ambient'\]"):
        bank.check_sensors(machine - {"ambient"})
    assert bank.usable(sim.model_id, machine) is sim
    for name in ("fl", "fl-by-hand"):  # both ch1_um: one store holds one target
        augmented.save(documents[name], tmp_path / "fl")
    bank = ModelBank.from_store(tmp_path / "fl", ambient_sensor="ambient")
    full, few = bank.get(documents["fl"]["model_id"]), bank.get(documents["fl-by-hand"]["model_id"])
    assert isinstance(few, BankedAugmented) and few.ambient_sensor is None
    assert bank.usable(full.model_id, machine) is full
    assert bank.usable(full.model_id, machine - {"T2"}) is few  # the fallback does without T2
    assert bank.usable(full.model_id, machine - {"T16", "T2"}) is None
    augmented.save(documents["sim"], tmp_path / "fl")  # error_um next to ch1_um: refused
    with pytest.raises(ValueError, match=r"predict different targets \(ch1_um \(µm\): "):
        ModelBank.from_store(tmp_path / "fl", ambient_sensor="ambient")


def test_effect_states_survive_a_restart(
    tmp_path: Path, documents: dict[str, dict], sim_prepared: Prepared
) -> None:
    augmented.save(documents["sim"], tmp_path / "store")
    bank = ModelBank.from_store(tmp_path / "store", ambient_sensor="ambient")
    model_id = documents["sim"]["model_id"]
    state_file = tmp_path / "state" / "m-effect-state.json"
    rows = list(rows_of(sim_prepared, StreamingAugmented(documents["sim"]).sensors))[:120]

    def rises_of(row: Row) -> dict[str, float]:
        assert row.ambient_rise_C is not None
        return row.rises_C | {"ambient": row.ambient_rise_C}

    # The gateway's cold reference is taken with the spindle stopped: n_ref = 0 r/min.
    reference = StreamingAugmented(documents["sim"])
    running = EffectStates(bank.augmented(), state_file, save_every_s=0.0)
    for row in rows[:60]:
        predicted = running.advance(row.time_s, rises_of(row), row.speed_rpm)
        expected = reference.step(row.time_s, row.rises_C, row.speed_rpm, row.ambient_rise_C)
        assert predicted == {model_id: expected}
    restarted = EffectStates(bank.augmented(), state_file)
    for row in rows[60:]:
        predicted = restarted.advance(row.time_s, rises_of(row), row.speed_rpm)
        expected = reference.step(row.time_s, row.rises_C, row.speed_rpm, row.ambient_rise_C)
        assert predicted == {model_id: expected}

    saved = json.loads(state_file.read_text(encoding="utf-8"))
    saved["models"][model_id]["sha256"] = "0" * 64  # the model was refitted since
    state_file.write_text(json.dumps(saved), encoding="utf-8")
    assert EffectStates(bank.augmented(), state_file).streams[model_id].time_s is None
