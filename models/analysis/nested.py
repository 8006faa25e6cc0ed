"""The residual analysis with every choice made without the run it is scored on.

:func:`models.analysis.search.analyze` chooses each effect's parameter (τ, sensor) inside
its folds, but whether an effect enters at all is judged on the pooled held-out
residual of *every* fold, the one reported among them; and a base model picked
because its analysis scored best is picked on the data it is scored on. Both make
its held-out figure somewhat optimistic.

Here the whole procedure runs inside an outer leave-one-run-out:

1. hold out one run (a block, for a single run; the same folds as the analysis);
2. on the other runs, analyse every candidate base model (its own leave-one-run-out
   inside, its own effect search) and keep the base whose analysis leaves the
   lowest held-out RMSE there (``BASE_CHOICE_RULE``);
3. fit that base and its effects on those runs (:func:`models.analysis.augmented.fit_augmented`)
   and predict the held-out run.

The pooled RMSE of those predictions is the procedure's figure on data no choice
saw. Every candidate's own nested figure comes out of the same runs (each base's
augmented model predicts the held-out run too); they are reported beside it, and
picking among *them* afterwards would be a choice on the scored data again.

The cost is one analysis per base and outer run: seconds per base for the
ordinary-least-squares bases, about ten for ``lag-ridge`` on ``fl_thermal.csv``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from tqdm import tqdm

from models.analysis.augmented import augmented_prediction
from models.analysis.result import AnalysisResult, HeldOutRun, NestedAnalysis
from models.analysis.search import Accepted, Folds, ResidualAnalysis, analyze
from models.data.features import Prepared
from models.fit.metrics import accuracy

#: ``analyze --model auto``'s candidates, from the plainest to the most flexible: a tie
#: goes to the plainer model.
AUTO_BASES = ("mlr", "ridge", "pls", "grey-mlr", "pca-quadratic", "lag-ridge")
#: An outer fold leaves this many runs at least, so the analysis inside still has folds.
MIN_TRAINING_RUNS = 2


@dataclass(frozen=True)
class BaseAnalysis:
    """One base model's residual analysis on a set of runs."""

    method: str
    result: AnalysisResult
    accepted: list[Accepted]
    analysis: ResidualAnalysis

    @cached_property
    def predicted_um(self) -> np.ndarray:
        """The augmented model fitted on the analysed rows, predicting every row. Made when
        asked (the nested loop scores each base with it; ``--model auto`` alone does not,
        and a lag-ridge base costs a whole fit)."""
        return augmented_prediction(self.analysis, self.accepted)

    @property
    def heldout_rmse_um(self) -> float:
        return self.result.after.rmse_um

    @property
    def effects(self) -> list[dict[str, Any]]:
        return [{"effect": step.effect, "params": step.params} for step in self.result.added_steps]


def analyse_bases(
    prepared: Prepared,
    methods: Sequence[str],
    sensors: Sequence[str] | None = None,
    fit_rows: np.ndarray | None = None,
) -> tuple[str, dict[str, BaseAnalysis]]:
    """Every base's analysis on ``fit_rows`` and the base ``BASE_CHOICE_RULE`` keeps."""
    analyses = {}
    for method in methods:
        result, accepted, analysis = analyze(prepared, method, sensors, fit_rows=fit_rows)
        analyses[method] = BaseAnalysis(method, result, accepted, analysis)
    chosen = min(methods, key=lambda m: (analyses[m].heldout_rmse_um, methods.index(m)))
    return chosen, analyses


def nested_analysis(
    prepared: Prepared,
    methods: Sequence[str],
    sensors: Sequence[str] | None = None,
    fit_rows: np.ndarray | None = None,
    progress: bool = False,
) -> NestedAnalysis:
    """Hold out each run in turn and run :func:`analyse_bases` on the others.

    ``fit_rows``: rows whose target is known (probe rows of a logged history); the
    held-out run is scored on its known rows only.
    """
    methods = tuple(dict.fromkeys(methods))
    if not methods:
        raise ValueError("nested analysis needs at least one base model")
    usable = np.ones(prepared.data.n_samples, bool) if fit_rows is None else np.asarray(fit_rows)
    folds = Folds.of(prepared, usable)
    if folds.count < MIN_TRAINING_RUNS + 1:
        raise ValueError(
            f"nested analysis needs at least {MIN_TRAINING_RUNS + 1} runs (or blocks) with a "
            f"target; found {folds.count}"
        )
    y = prepared.error_um
    runs: list[HeldOutRun] = []
    measured: list[np.ndarray] = []
    predicted: dict[str, list[np.ndarray]] = {m: [] for m in (*methods, "chosen")}
    outer = tqdm(
        range(folds.count), desc="held-out runs", disable=not progress, leave=False, unit="run"
    )
    for k in outer:
        held = folds.rows[k]
        train = usable.copy()
        train[held] = False
        chosen, analyses = analyse_bases(prepared, methods, sensors, train)
        measured.append(y[held])
        rmse = {}
        for m in (*methods, "chosen"):
            guess = analyses[chosen if m == "chosen" else m].predicted_um[held]
            predicted[m].append(guess)
            rmse[m] = accuracy(y[held], guess).rmse_um
        runs.append(
            HeldOutRun(
                run=folds.names[k],
                rows=int(held.size),
                chosen=chosen,
                inner_rmse_um={m: a.heldout_rmse_um for m, a in analyses.items()},
                effects={m: a.effects for m, a in analyses.items()},
                rmse_um=rmse,
            )
        )
    return NestedAnalysis(
        target=prepared.data.target,
        methods=methods,
        scheme=folds.scheme,
        runs=tuple(runs),
        measured_um=np.concatenate(measured),
        predicted_um={m: np.concatenate(p) for m, p in predicted.items()},
    )
