"""The interval widened by the time since the last probe, in the running gateway.

The simulated machine hides a drift the fitted models lack, and its probe cycle writes
the measured error into macro #600 every 300 s. The gateway (RTU transmitters over a
socat pty pair, the CNC over OPC UA, one manual clock) runs the same programme with the
online correction off and on. Off, no probe changes the interval; on, each cycle's
half-width is the one without the correction widened in quadrature by the variance the
filter gained since its last accepted probe: √(w² + z² · q · Δt), the ``bias`` kind's
random walk (q µm²/h, Δt h), z = 1.645 for the 90 % interval.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import pytest

from gateway.config import CompensationSection, OnlineCorrectionSection
from gateway.live.record import CycleRecord
from simulator.programs import production_program
from tests import gateway_rig as rig
from tests.test_closed_loop import CYCLE_S, closed_loop

PROBE_MACRO = 600  # where the simulator's probe cycle writes (simulator/machine.yaml)
PROGRAM = production_program(seed=31, duration_s=1.5 * 3600.0)
PROCESS_UM2_PER_H = 4.0
Z_90 = 1.6448536269514722


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("interval-probe"))


async def records_of(tmp_path: Path, store: Path, enabled: bool) -> list[CycleRecord]:
    correction = OnlineCorrectionSection(
        enabled=enabled, process_um2_per_h=PROCESS_UM2_PER_H, probe_noise_um=0.3, bound_um=20.0
    )
    compensation = CompensationSection(
        macro=500, unit="mm", clamp_um=50.0, slew_um_per_min=20.0, probe_macro=PROBE_MACRO
    )
    update = {"compensation": compensation, "online_correction": correction}
    tmp_path.mkdir()
    async with closed_loop(tmp_path, store, PROGRAM, effects=("drift",), update=update) as (
        closed,
        clock,
    ):
        for _ in range(int(PROGRAM.duration_s // CYCLE_S)):
            clock.advance(CYCLE_S)
            await closed.plant.update()
            await closed.loop.run_cycle()
        return list(closed.trace.records)


def test_interval_widens_with_the_time_since_the_last_probe(tmp_path: Path, store: Path) -> None:
    async def scenario() -> tuple[list[CycleRecord], list[CycleRecord]]:
        off = await records_of(tmp_path / "off", store, enabled=False)
        on = await records_of(tmp_path / "on", store, enabled=True)
        return off, on

    off, on = asyncio.run(scenario())
    assert len(off) == len(on) and len(on) > 100
    probes_off = [r for r in off if r.probe_error_um is not None]
    assert len(probes_off) >= 10, "the probe cycle never wrote #600"
    assert all(r.correction_um is None for r in off)

    # A cycle whose bus went unanswered past its timeout (the test machine descheduled
    # that long under load) has no interval in that run only; at most 1 % of them.
    unanswered = {
        k for k, (a, b) in enumerate(zip(off, on, strict=True)) if a.link_errors or b.link_errors
    }
    assert len(unanswered) <= 0.01 * len(on), unanswered

    last_probe_s: float | None = None
    widened = 0
    for k, (a, b) in enumerate(zip(off, on, strict=True)):
        assert a.time_s == b.time_s
        if k in unanswered or a.interval_um is None:
            assert k in unanswered or b.interval_um is None
        else:
            assert b.interval_um is not None
            if last_probe_s is None:
                assert b.interval_um == a.interval_um  # no correction yet: nothing to add
            else:
                hours = (b.time_s - last_probe_s) / 3600.0
                expected = math.sqrt(a.interval_um**2 + Z_90**2 * PROCESS_UM2_PER_H * hours)
                assert math.isclose(b.interval_um, expected, rel_tol=1e-9), (b.time_s, last_probe_s)
                widened += b.interval_um > a.interval_um
        # the filter takes the probe read this cycle at its end (after the interval)
        if accepted(b):
            last_probe_s = b.time_s
    assert widened > 100

    # each accepted probe takes the width back down on the next cycle
    def ratio(k: int) -> float:
        a, b = off[k].interval_um, on[k].interval_um
        assert a is not None and b is not None
        return b / a

    taken = [k for k, r in enumerate(on[:-1]) if accepted(r)]
    assert len(taken) >= 10
    drops = [
        (ratio(k), ratio(k + 1))
        for k in taken[1:]
        if not {k, k + 1} & unanswered and off[k].interval_um and off[k + 1].interval_um
    ]
    assert len(drops) >= len(taken) - 3
    assert all(before > 1.5 and after < before for before, after in drops), drops


def accepted(record: CycleRecord) -> bool:
    """Whether the online correction took the probe read in this cycle."""
    return (
        record.probe_error_um is not None
        and not record.probe_refused
        and record.correction_um is not None
    )
