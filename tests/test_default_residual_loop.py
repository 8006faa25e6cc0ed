"""The residual loop on the default base (lag-ridge): each simulator effect is named and cut.

With no ``--model`` the base is lag-ridge, whose own lags (5 min … 24 h of every
sensor and of the speed) hold a thermal lag, a speed-direct growth or an unsensed
heat path already; a drift or an ambient-driven error is an input it lacks, found by
refitting it with that input on each fold's training runs
(:mod:`models.analysis.inside`). For each effect either the effect is named and the
held-out RMSE falls by at least 30 %, or the base already holds it (held-out RMSE
before within 1.3 × the probe's noise) and nothing else is named; a recording with
no effect stays ``none``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from models.analysis.search import analyze
from models.data.dataset import load_runs
from models.data.features import prepare
from tests.test_analyze import PARAMS, simulated

NOISE_LIMIT_UM = 1.3 * PARAMS.probe.noise_um


def analysed_by_default(path: Path):
    result, _, _ = analyze(prepare(load_runs(path, target="error_um")), "lag-ridge")
    return result


@pytest.mark.parametrize("effect", ["drift", "ambient", "thermal_lag", "speed_direct"])
@pytest.mark.parametrize("seed", [1, 2])
def test_default_base_names_the_effect_or_already_holds_it(
    tmp_path: Path, effect: str, seed: int
) -> None:
    result = analysed_by_default(simulated(tmp_path, effect, seed))
    evidence = [c.as_dict() for c in result.steps[0].candidates]
    if result.before.rmse_um <= NOISE_LIMIT_UM:
        assert result.effect in (effect, "none"), evidence
    else:
        assert result.effect == effect, (result.before.rmse_um, evidence)
        assert result.after.rmse_um <= 0.7 * result.before.rmse_um


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_default_base_without_an_effect_stays_none(tmp_path: Path, seed: int) -> None:
    result = analysed_by_default(simulated(tmp_path, "none", seed))
    assert result.effect == "none", [c.as_dict() for c in result.steps[0].candidates]
    assert result.after == result.before
