"""Residual analysis restricted to some rows' target, the terms built on the whole history.

``ResidualAnalysis(fit_rows=…)`` uses the target of those rows only, while every
effect term (lags since the recording's reference) still runs over every row: what
a held-out run, or a log with the error known only at probe rows, needs.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from models.analysis.search import ResidualAnalysis
from models.data.dataset import load_runs
from models.data.features import prepare
from tests.cli import ROOT


def chosen(analysis: ResidualAnalysis) -> list[tuple[str, dict]]:
    _, accepted = analysis.run()
    return [(a.family.effect, a.params) for a in accepted]


def test_rows_outside_fit_rows_never_steer_the_analysis():
    prepared = prepare(load_runs(ROOT / "data" / "fl_thermal.csv", target="ch1_um"))
    held_out = prepared.data.run == prepared.data.run_ids[2]
    first = ResidualAnalysis(prepared, "mlr", fit_rows=~held_out)
    assert first.folds.count == 5  # one fold per training run, none for the held-out one
    effects = chosen(first)
    # The held-out run's target replaced by anything: the same effects, the same figures.
    scrambled = replace(
        prepared,
        error_um=np.where(held_out, 100.0 * np.sin(prepared.data.time_s), prepared.error_um),
    )
    second = ResidualAnalysis(scrambled, "mlr", fit_rows=~held_out)
    assert chosen(second) == effects
    # …whereas with every row in, the analysis sees that run and its choice can move.
    everything = ResidualAnalysis(scrambled, "mlr")
    assert everything.folds.count == 6
    assert chosen(everything) != effects
