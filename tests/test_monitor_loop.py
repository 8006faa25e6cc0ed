"""The residual monitor in the running gateway, over the real protocols, end to end.

The simulated machine hides a ``drift`` (1.5 µm/h from the programme's start) the
fitted models lack; its probe cycle writes the measured error into macro #600
every 300 s. The gateway's loop (RTU transmitters over a socat pty pair, the CNC
over OPC UA, one manual clock) runs with the monitor attached as in ``run``: the
monitor's background process analyses the logged history after an alarm and
publishes a proposal in the model store; the operator promotes it
(``ProposalStore.versions.promote``, what ``models promote`` does); the running
loop swaps it in between cycles. Compensated RMSE over the next four hours must
be ≤ 0.7 × that of the four hours before the proposal.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from gateway.app import attach_monitors
from gateway.config import CompensationSection, MonitorSection
from models.proposals import ProposalStore
from simulator.programs import production_program
from tests.test_closed_loop import CYCLE_S, assert_every_write_was_safe, closed_loop

PROBE_MACRO = 600
PROGRAM = production_program(seed=41, duration_s=14 * 3600.0)
BOUND_S = 8 * 3600.0  # machine time within which the drift must be proposed
NEXT_S = 4 * 3600.0


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from gateway.demo import fit_models, write_training_data

    folder = tmp_path_factory.mktemp("monitor-loop")
    write_training_data(folder / "training.csv", seed=1)
    fit_models(folder / "training.csv", folder / "models", "test")
    return folder / "models"


def test_drift_proposed_promoted_and_removed_over_the_protocols(
    tmp_path: Path, fitted: Path, caplog: pytest.LogCaptureFixture
):
    caplog.set_level(logging.INFO, logger="gateway.monitor")
    store = tmp_path / "models"
    shutil.copytree(fitted, store)
    compensation = CompensationSection(
        macro=500, unit="mm", clamp_um=50.0, slew_um_per_min=20.0, probe_macro=PROBE_MACRO
    )
    update = {"compensation": compensation, "monitor": MonitorSection(enabled=True)}

    async def scenario():
        (tmp_path / "rig").mkdir()
        async with closed_loop(
            tmp_path / "rig", store, PROGRAM, effects=("drift",), update=update
        ) as (closed, clock):
            monitors = attach_monitors([closed.loop], tmp_path / "state")
            monitor = monitors[closed.loop.config.id]
            start = clock.now()
            try:
                while not monitor.state.proposals and clock.now() - start < BOUND_S:
                    await closed.step(clock)
                    if monitor.analysing:  # seconds of wall time: as it would within a cycle
                        await asyncio.to_thread(monitor.wait, 300.0)
                proposed_s = clock.now() - start
                assert monitor.state.proposals, [a.describe() for a in monitor.state.alarms]
                summary = monitor.state.proposals[0]
                proposals = ProposalStore(store)
                published = proposals.list(machine_id=closed.loop.config.id)
                assert [p.id for p in published] == [summary["proposal_id"]]
                proposal = published[0]
                assert proposal.effect == "drift" and proposal.probe_rows >= 24
                assert proposal.after_rmse_um < proposal.before_rmse_um
                proposed_at = len(closed.trace.records)
                proposals.versions.promote(proposal.id, by="operator")
                for _ in range(int(NEXT_S // CYCLE_S)):
                    await closed.step(clock)
            finally:
                for m in monitors.values():
                    m.close()
            assert_every_write_was_safe(closed)
            return closed, proposal, proposed_s, proposed_at

    closed, proposal, proposed_s, proposed_at = asyncio.run(scenario())
    assert proposed_s <= BOUND_S
    window = int(NEXT_S // CYCLE_S)
    errors = np.asarray(closed.trace.compensated_um)
    before = float(np.sqrt(np.mean(errors[max(proposed_at - window, 0) : proposed_at] ** 2)))
    after = float(np.sqrt(np.mean(errors[proposed_at:] ** 2)))
    used = {r.model_id for r in closed.trace.records[proposed_at + 2 :]}
    assert used == {proposal.model_id}, used
    assert after <= 0.7 * before, (before, after)
    # In the logs: the alarm, the proposal, its publication; and the evidence restarted.
    text = caplog.text
    assert "residual analysis of" in text and "started in the background" in text
    assert "residual monitor proposes drift" in text
    assert f"published proposal {proposal.id}" in text
    assert f"model {proposal.model_id} in use; the tests start afresh" in text
