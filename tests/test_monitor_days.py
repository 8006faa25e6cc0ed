"""The residual monitor over days of machine time: the simulator's physics in-process.

The machine hides an effect the fitted model lacks (the demo's models, fitted on
runs without it) and probes every 300 s; the monitor, fed every cycle as a loop
sink, must propose that effect within a bounded machine time, and the proposal,
once promoted, must cut the compensated RMSE over the next day to ≤ 0.7 × what the
same day gives without it. Without a hidden effect, ten days give no proposal.
The same path over the real protocols is ``tests/test_monitor_loop.py``.
"""

from __future__ import annotations

import copy
from pathlib import Path

import pytest

from gateway.demo.monitor_phase import SENSORS, InProcessPlant, programme_days
from gateway.live.proposal_monitor import MonitorSink
from models.online.correction import CorrectionParams
from models.online.residual_monitor import MonitorParams
from tests.gateway_rig import fit_store

DAY_S = 86400.0
#: Machine time within which the effect must be proposed.
BOUND_S = {"drift": 12 * 3600.0, "thermal_lag": 14 * 3600.0}  # as over the protocols
MONITOR_FILTER = CorrectionParams(process_um2_per_h=0.1)


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return fit_store(tmp_path_factory.mktemp("monitor-days"))


def monitored(store: Path, effects: tuple[str, ...], seed: int, days: int):
    plant = InProcessPlant(store, programme_days(seed, days), effects, seed=seed)
    sink = MonitorSink(
        "vmc", SENSORS, MonitorParams(), MONITOR_FILTER, cycle_s=15.0, in_process=True
    )
    plant.sinks.append(sink)
    return plant, sink


@pytest.mark.parametrize("effect", ["drift", "thermal_lag"])
def test_the_missing_effect_is_proposed_and_promoting_it_helps(store: Path, effect: str):
    plant, sink = monitored(store, (effect,), seed=3, days=4)
    took_s = plant.run_for(BOUND_S[effect], until=lambda: bool(sink.state.proposals))
    assert sink.state.proposals, (effect, [a.describe() for a in sink.state.alarms])
    assert took_s <= BOUND_S[effect]
    proposal = sink.state.proposals[0]
    assert proposal["effects"][0]["effect"] == effect
    assert proposal["after"]["rmse_um"] < proposal["before"]["rmse_um"]
    # The next day twice: as it is, and with the proposal promoted.
    kept = copy.deepcopy(plant)
    kept.sinks.clear()
    plant.sinks.clear()
    plant.promote(proposal["document"])
    start = len(plant.errors_um)
    kept.run_for(DAY_S)
    plant.run_for(DAY_S)
    day = len(plant.errors_um) - start
    before, after = kept.rmse_um(last=day), plant.rmse_um(last=day)
    assert after <= 0.7 * before, (before, after)


def test_no_hidden_effect_no_proposal_in_ten_days(store: Path):
    plant, sink = monitored(store, (), seed=4, days=10)
    plant.run_for(10 * DAY_S)
    assert sink.state.probes >= 2800  # one every 300 s
    assert not sink.state.proposals, sink.state.proposals
    # Alarms, if any, only started analyses; the design allows 1 per month.
    assert len(sink.state.alarms) <= 3, [a.describe() for a in sink.state.alarms]
