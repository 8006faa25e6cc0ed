"""The online correction in the running gateway, over the real protocols.

The simulated machine hides a ``drift`` (probe/fixture creep, 1.5 µm/h) the
fitted models lack, and its probe cycle writes the measured error into macro
#600 every 300 s. The gateway (RTU transmitters over a socat pty pair, the CNC
over OPC UA, one manual clock) runs the same programme three times: without
the correction, with it, and with it and a chip under the probe once (+30 µm).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from gateway.config import CompensationSection, OnlineCorrectionSection
from simulator.closed_loop import ClosedLoop
from simulator.programs import production_program
from tests import gateway_rig as rig
from tests.test_closed_loop import CYCLE_S, assert_every_write_was_safe, closed_loop

PROBE_MACRO = 600  # where the simulator's probe cycle writes (simulator/machine.yaml)
PROGRAM = production_program(seed=31, duration_s=4 * 3600.0)
CHIP_UM = 30.0
CHIP_AT_PROBE = 30  # the 30th probe measurement (2.5 h in) has a chip under it


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("online-loop"))


async def replayed(
    tmp_path: Path, store: Path, enabled: bool, chip_at_probe: int | None = None
) -> ClosedLoop:
    """One run of the programme; the probe value read by the gateway is the machine's own,
    except at probe number ``chip_at_probe``."""
    correction = OnlineCorrectionSection(
        enabled=enabled, process_um2_per_h=1.0, probe_noise_um=0.3, bound_um=20.0
    )
    compensation = CompensationSection(
        macro=500, unit="mm", clamp_um=50.0, slew_um_per_min=20.0, probe_macro=PROBE_MACRO
    )
    update = {"compensation": compensation, "online_correction": correction}
    tmp_path.mkdir()
    loop = closed_loop(tmp_path, store, PROGRAM, effects=("drift",), update=update)
    async with loop as (closed, clock):
        plant = closed.plant.machine
        last, probes, chipped = plant.macros[PROBE_MACRO], 0, False
        for _ in range(int(PROGRAM.duration_s // CYCLE_S)):
            clock.advance(CYCLE_S)
            await closed.plant.update()
            if plant.macros[PROBE_MACRO] != last:
                probes += 1
                # The chip comes with the first probe from number ``chip_at_probe`` on that
                # follows a cycle with a prediction (the filter needs the one it measures).
                previous = closed.trace.records[-1] if closed.trace.records else None
                if (
                    chip_at_probe is not None
                    and not chipped
                    and probes >= chip_at_probe
                    and previous is not None
                    and previous.predicted_um is not None
                ):
                    plant.macros[PROBE_MACRO] += CHIP_UM
                    await closed.plant.update()
                    chipped = True
                last = plant.macros[PROBE_MACRO]
            await closed.loop.run_cycle()
        assert chip_at_probe is None or chipped
        assert_every_write_was_safe(closed)
        return closed


def test_probe_correction_removes_the_drift_and_ignores_a_chip(tmp_path: Path, store: Path):
    async def scenario() -> tuple[ClosedLoop, ClosedLoop]:
        without = await replayed(tmp_path / "without", store, enabled=False)
        with_ = await replayed(tmp_path / "with", store, enabled=True, chip_at_probe=CHIP_AT_PROBE)
        return without, with_

    without, with_ = asyncio.run(scenario())
    second_half = slice(len(without.trace.time_s) // 2, None)
    rmse = {
        name: float(np.sqrt(np.mean(np.asarray(c.trace.compensated_um)[second_half] ** 2)))
        for name, c in (("without", without), ("with", with_))
    }
    assert rmse["without"] > 2.0, rmse  # the drift the model lacks
    assert rmse["with"] <= 0.4 * rmse["without"], rmse
    records = with_.trace.records
    probes = [i for i, r in enumerate(records) if r.probe_error_um is not None]
    assert len(probes) >= 40  # one every 300 s over 4 h
    later = [r for r in records[len(records) // 2 :] if r.predicted_um is not None]
    assert later and all(r.correction_um is not None for r in later)

    # The chip: refused, and the compensation hardly moved.
    assert with_.loop.online is not None and with_.loop.online.refused >= 1
    chip = next(i for i in probes if records[i].probe_error_um > CHIP_UM - 5.0)
    assert records[chip].probe_refused
    assert sum(r.probe_refused for r in records) == with_.loop.online.refused
    # The last correction applied before the probe was read, and the next one after.
    before = next(r for r in reversed(records[: chip + 1]) if r.correction_um is not None)
    after = next(r for r in records[chip + 1 :] if r.correction_um is not None)
    assert before.correction_um is not None
    assert abs(after.correction_um - before.correction_um) < 0.5
    assert before.applied_um is not None and after.applied_um is not None
    assert before.predicted_um is not None and after.predicted_um is not None
    moved = abs(after.applied_um - before.applied_um)
    assert moved < 1.0 + abs(after.predicted_um - before.predicted_um), (moved, before, after)
