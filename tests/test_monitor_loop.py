"""The residual monitor in the running gateway, over the real protocols, end to end.

The simulated machine hides an effect the fitted models lack: a ``drift`` (1.5 µm/h
from the programme's start) or a ``thermal_lag`` (80 % of the shaft's growth through
a 30 min lag); its probe cycle writes the measured error into macro #600 every
300 s. The gateway runs as ``run`` builds it (:class:`gateway.wiring.Gateway`: the
loop with its RTU transmitters over a socat pty pair, the CNC over OPC UA, the
monitor attached, the SCADA server), all on one manual clock. The monitor's
background process analyses the logged history after an alarm and publishes a
proposal in the model store, which must name the hidden effect within a bounded
machine time (``BOUND_S``). A SCADA client (asyncua, SignAndEncrypt) reads the
proposal; a viewer's call of ``PromoteProposal`` is refused, an operator's
promotes it, and the running loop swaps the model in between cycles. Compensated
RMSE at the tool over the next four hours of the programme must be ≤ 0.7 × that
of the four hours before the promotion.

Why the bounds differ: a drift is a steady trend in the residual, believed by the
analysis from a few hours of probes; a lag shows only around speed changes. The
monitor's tests alarm within the first hours either way, but the residual analysis
(:mod:`models.analysis.search`: every training fold's F-test, τ chosen inside each fold)
believes the lag only once the history holds some 80–110 probes of heating and
cooling; the analyses of shorter histories find no effect, and the next alarm
starts the next one. Measured in-process (tests/test_monitor_days.py's plant,
seeds 3–19): 6.8–9.0 h at a probe every 300 s, 3.2–4.8 h at one every 150 s (two
of six then naming ``unsensed_heat``, a lag of another kind), so it is the probes,
not the monitor's tests, that set the time.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from asyncua import Client, ua

from drivers.clock import ManualClock
from gateway.config import CompensationSection, GatewayConfig, MachineSection, MonitorSection
from gateway.wiring import Gateway
from models.online.proposals import PROMOTED, ProposalStore
from simulator.closed_loop import ClosedLoop
from simulator.programs import production_program
from simulator.serve import SimulatedPlant
from tests import gateway_rig as rig
from tests.test_closed_loop import CYCLE_S, assert_every_write_was_safe, closed_loop
from tests.test_promotion import OPERATOR, VIEWER, scada_client, scada_gateway

PROBE_MACRO = 600
#: Machine time within which the hidden effect must be proposed.
BOUND_S = {"drift": 8 * 3600.0, "thermal_lag": 14 * 3600.0}
NEXT_S = 4 * 3600.0
SCADA_WAIT_S = 60.0  # wall time a SCADA node may take to show a cycle (generous: slow CI)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("monitor-loop"))


@dataclass
class GatewayOpener:
    """Opens the loop as ``run`` does: a whole :class:`Gateway` (monitor, SCADA) of the
    machine ``closed_loop`` configures, its SCADA server started. The state goes to
    the ``state_dir`` of ``sections`` (``closed_loop``'s is for a bare loop)."""

    sections: dict[str, Any]  # the gateway-wide config sections
    app: Gateway | None = None

    async def __call__(
        self,
        plant: SimulatedPlant,
        machine: MachineSection,
        clock: ManualClock,
        *,
        state_dir: Path | None = None,
    ) -> ClosedLoop:
        await plant.start()
        config = GatewayConfig.model_validate({"machines": [machine], **self.sections})
        self.app = Gateway(config, clock=clock)
        assert self.app.scada is not None
        await self.app.scada.start()
        return ClosedLoop(plant, self.app.loops[0])


async def eventually(read: Any, expected: Any) -> Any:
    """The node's value once it equals ``expected`` (the SCADA publish runs in tasks);
    the last value read after ``SCADA_WAIT_S`` of wall time otherwise."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + SCADA_WAIT_S
    while (value := await read()) != expected and loop.time() < deadline:
        await asyncio.sleep(0.05)
    return value


@pytest.mark.parametrize("effect", ["drift", "thermal_lag"])
def test_hidden_effect_proposed_promoted_over_scada_and_removed_over_the_protocols(
    tmp_path: Path, fitted: Path, caplog: pytest.LogCaptureFixture, effect: str
):
    caplog.set_level(logging.INFO, logger="gateway")
    store = tmp_path / "models"
    shutil.copytree(fitted, store)
    program = production_program(seed=41, duration_s=BOUND_S[effect] + NEXT_S)
    compensation = CompensationSection(
        macro=500, unit="mm", clamp_um=50.0, slew_um_per_min=20.0, probe_macro=PROBE_MACRO
    )
    update = {"compensation": compensation, "monitor": MonitorSection(enabled=True)}
    opener = GatewayOpener(scada_gateway(tmp_path))

    async def scenario():
        (tmp_path / "rig").mkdir()
        clients: list[Client] = []
        async with closed_loop(
            tmp_path / "rig", store, program, effects=(effect,), update=update, opener=opener
        ) as (closed, clock):
            app = opener.app
            assert app is not None and app.scada is not None
            machine_id = closed.loop.config.id
            monitor = app.monitors[machine_id]
            start = clock.now()
            try:
                while not monitor.state.proposals and clock.now() - start < BOUND_S[effect]:
                    await closed.step(clock)
                    if monitor.analysing:  # seconds of wall time: as it would within a cycle
                        await asyncio.to_thread(monitor.wait, 300.0)
                proposed_s = clock.now() - start
                assert monitor.state.proposals, [a.describe() for a in monitor.state.alarms]
                summary = monitor.state.proposals[0]
                published = ProposalStore(store).list(machine_id=machine_id)
                assert [p.id for p in published] == [summary["proposal_id"]]
                proposal = published[0]
                assert proposal.effect == effect and proposal.probe_rows >= 24
                assert proposal.after_rmse_um < proposal.before_rmse_um
                await closed.step(clock)  # the loop sees the store's new proposal

                # Over SCADA: the proposal is shown; a viewer may not promote it, an operator may.
                ns = app.scada.namespace_index
                pki = app.config.scada.pki_dir  # type: ignore[union-attr]
                viewer = await scada_client(app.scada.endpoint, pki, tmp_path / "v", VIEWER)
                clients.append(viewer)
                operator = await scada_client(app.scada.endpoint, pki, tmp_path / "o", OPERATOR)
                clients.append(operator)

                def node(name: str) -> Any:
                    return viewer.get_node(ua.NodeId(f"{machine_id}.{name}", ns))

                newest = node("Proposals.NewestId")
                assert await eventually(newest.read_value, proposal.id) == proposal.id
                assert await node("Proposals.NewestEffect").read_value() == effect
                params = json.loads(await node("Proposals.NewestParamsJson").read_value())
                assert params == proposal.params
                after_um = await node("Proposals.NewestAfterUm").read_value()
                assert after_um == pytest.approx(proposal.after_rmse_um)
                promote = ua.NodeId(f"{machine_id}.PromoteProposal", ns)
                as_viewer = viewer.get_node(ua.NodeId(machine_id, ns))
                with pytest.raises(ua.UaStatusCodeError) as refused:
                    await as_viewer.call_method(promote, proposal.id)
                assert refused.value.code == ua.StatusCodes.BadUserAccessDenied
                assert ProposalStore(store).get(proposal.id).status == "proposed"
                as_operator = operator.get_node(ua.NodeId(machine_id, ns))
                answer = await as_operator.call_method(promote, proposal.id)
                assert "version 1" in answer and proposal.id in answer
                promoted_at = len(closed.trace.records)
                for _ in range(int(NEXT_S // CYCLE_S)):
                    await closed.step(clock)
                status = await eventually(node("Proposals.NewestStatus").read_value, PROMOTED)
                assert status == PROMOTED
                assert await node("ModelId").read_value() == proposal.model_id
            finally:
                for client in clients:
                    await client.disconnect()
                await app.scada.stop()
                for m in app.monitors.values():
                    m.close()
            assert_every_write_was_safe(closed)
            assert not closed.loop.sink_failures  # points, monitor, SCADA, heartbeat: every cycle
            return closed, proposal, proposed_s, promoted_at

    closed, proposal, proposed_s, promoted_at = asyncio.run(scenario())
    assert proposed_s <= BOUND_S[effect]
    window = int(NEXT_S // CYCLE_S)
    errors = np.asarray(closed.trace.compensated_um)
    before = float(np.sqrt(np.mean(errors[max(promoted_at - window, 0) : promoted_at] ** 2)))
    after = float(np.sqrt(np.mean(errors[promoted_at:] ** 2)))
    used = {r.model_id for r in closed.trace.records[promoted_at + 1 :]}
    assert used == {proposal.model_id}, used
    assert math.isfinite(before) and after <= 0.7 * before, (before, after)
    print(  # the figures, shown with -s
        f"{effect}: proposed after {proposed_s / 3600:.2f} h; compensated RMSE "
        f"{before:.2f} µm over the 4 h before promotion, {after:.2f} µm over the 4 h after"
    )
    # In the logs: the alarm, the proposal, its publication, the operator's promotion
    # over SCADA (the viewer's refused at the access check), and the evidence restarted.
    text = caplog.text
    assert "residual analysis of" in text and "started in the background" in text
    assert f"residual monitor proposes {effect}" in text
    assert f"published proposal {proposal.id}" in text
    assert f"SCADA operator on {closed.loop.config.id}: PromoteProposal({proposal.id})" in text
    assert f"model {proposal.model_id} in use; the tests start afresh" in text
