"""Simulated production with nights and a weekend off: the default model fitted on the first
week, run forward on the next, holds the same lag states in ``score`` and in the runtime.

The simulator runs one machine for 15 days: each weekday the spindle runs a random job-shop
programme from 07:00 for 9 h and rests the rest of the day (the night: the gateway runs on and
logs the machine at rest), and the weekend it is stopped with the gateway (no rows for two
days). Week 1 (Monday to Friday) is the training file; week 2 and the Monday after its
weekend are the later file. The gateway keeps its cold reference and every lag state
across a stop (``gateway/live/reference.py``, :mod:`gateway.live.bank.lag_state`), so the
later file is one recording with a 48 h logging gap: ``score`` takes it so when the model
was fitted with ``--reference recording-start``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from gateway.live.bank.lag_state import EffectStates
from gateway.live.bank.model_bank import ModelBank
from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.lag_ridge import lag_terms
from models.fit.workflow import fit_and_store
from models.online.streaming import BASE_PREFIX
from models.store import ModelStore, load_file
from simulator.params import load_params
from simulator.programs import SpeedProgram, production_program
from simulator.record import record
from tests.cli import gateway

DAY_S = 86400.0
SHIFT_START_S = 7 * 3600.0


def _fortnight() -> SpeedProgram:
    """15 days from a Monday 00:00: weekdays a 9 h random programme from 07:00, weekends at rest."""
    segments: list[tuple[float, float]] = []
    for day in range(15):
        if day % 7 >= 5:
            segments.append((DAY_S, 0.0))
            continue
        shift = production_program(day, duration_s=9 * 3600.0).segments[:-1]
        rest = DAY_S - SHIFT_START_S - sum(d for d, _ in shift)
        segments += [(SHIFT_START_S, 0.0), *shift, (rest, 0.0)]
    return SpeedProgram("fortnight", tuple(segments))


@pytest.fixture(scope="module")
def weeks(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(week 1, week 2 + Monday) as CSV files, one run per day, no rows on weekends."""
    folder = tmp_path_factory.mktemp("weeks")
    recording = record(load_params(), [_fortnight()], sample_s=120.0)
    time_index = recording.header.index("time_s")
    early, later = folder / "week1.csv", folder / "week2.csv"
    with early.open("w", newline="") as one, later.open("w", newline="") as two:
        writers = csv.writer(one), csv.writer(two)
        for writer in writers:
            writer.writerow(recording.header)
        for row in recording.rows:
            day = int(float(row[time_index]) // DAY_S)
            if day % 7 >= 5 or day >= 15:
                continue  # the weekend: machine and gateway stopped
            writers[day >= 7].writerow([f"day{day + 1:02d}", *row[1:]])
    return early, later


def test_score_and_the_runtime_hold_the_same_lag_states_through_restarts_and_a_weekend(
    weeks: tuple[Path, Path], tmp_path: Path
) -> None:
    early, later = weeks
    store = ModelStore(tmp_path / "store")
    trained = prepare(load_runs(early, target="error_um"), reference="recording-start")
    outcome = fit_and_store(trained, "lag-ridge", store)
    assert outcome is not None
    bank = ModelBank.from_store(store.root)
    (banked,) = bank.models.values()
    model, _ = load_file(store.path_of(banked.model_id))

    data = load_runs(later, target="error_um")
    forward = prepare(data, reference=trained.plan.policy)
    assert len(forward.plan.recording_runs) == 1  # one recording through the weekend gap
    time_s = forward.data.time_s
    assert np.diff(time_s).max() > 2 * DAY_S  # the weekend stop is a logging gap
    batch = model.predict(forward.inputs)
    terms = lag_terms(forward.inputs, model.sensors_used_, model.lag_taus_s, model.speed_powers)

    wednesday = int(np.searchsorted(time_s, 9 * DAY_S + 12 * 3600.0))  # a warm restart
    monday = int(np.flatnonzero(np.diff(time_s) > DAY_S)[0]) + 1  # after the weekend off
    state_file = tmp_path / "m1-effect-state.json"
    states = EffectStates(bank.augmented(), state_file)
    streamed, lag_states = [], {}
    for k in range(forward.data.n_samples):
        if k in (wednesday, monday):  # the gateway stops; it starts again from its files
            states.save()
            states = EffectStates(ModelBank.from_store(store.root).augmented(), state_file)
        rises = dict(zip(forward.inputs.sensors, forward.inputs.rise_C[k], strict=True))
        value = states.advance(float(time_s[k]), rises, float(forward.data.speed_rpm[k]))
        streamed.append(value[banked.model_id])
        if k in (0, wednesday, monday, forward.data.n_samples - 1):
            saved = states.streams[banked.model_id].export_state()
            lag_states[k] = np.array([saved[key] for key in _lag_keys(model)])
    assert np.max(np.abs(np.array(streamed) - batch)) < 1e-9
    width = len(model.sensors_used_) + len(model.speed_powers)
    for k, held in lag_states.items():  # every lag state, at each start and at the end
        assert np.max(np.abs(held - terms[k, width:])) < 1e-9, k
    # The cold start has every lag at its input.
    assert np.allclose(lag_states[0], np.tile(terms[0, :width], len(model.lag_taus_s)))

    score_json = tmp_path / "score.json"
    done = gateway(
        "score", later, "--model", banked.model_id, "--store", store.root, "--json", score_json
    )
    assert done.returncode == 0, done.stderr
    scored = json.loads(score_json.read_text())["pooled"]
    runtime_rmse = float(np.sqrt(np.mean((forward.error_um - np.array(streamed)) ** 2)))
    assert scored["n_samples"] == forward.data.n_samples
    assert scored["rmse_um"] == pytest.approx(runtime_rmse, rel=1e-9)


def _lag_keys(model) -> list[str]:
    """The runtime's keys of the lag-ridge's lag states (its base stream's, prefixed)."""
    return [BASE_PREFIX + key for key in model.stream().state_keys()]
