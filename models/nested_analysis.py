"""The residual analysis with every choice made without the run it is scored on.

:func:`models.analysis.analyze` chooses each effect's parameter (τ, sensor) inside
its folds, but whether an effect enters at all is judged on the pooled held-out
residual of *every* fold, the one reported among them; and a base model picked
because its analysis scored best is picked on the data it is scored on. Both make
its held-out figure somewhat optimistic.

Here the whole procedure runs inside an outer leave-one-run-out:

1. hold out one run (a block, for a single run; the same folds as the analysis);
2. on the other runs, analyse every candidate base model (its own leave-one-run-out
   inside, its own effect search) and keep the base whose analysis leaves the
   lowest held-out RMSE there (``BASE_CHOICE_RULE``);
3. fit that base and its effects on those runs (:func:`models.augmented.fit_augmented`)
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

from models.analysis import Accepted, Folds, ResidualAnalysis, analyze
from models.analysis_render import Row, columns
from models.analysis_result import AnalysisResult
from models.augmented import augmented_prediction
from models.features import Prepared
from models.metrics import Accuracy, accuracy

#: ``analyze --model auto``'s candidates, from the plainest to the most flexible: a tie
#: goes to the plainer model.
AUTO_BASES = ("mlr", "ridge", "pls", "grey-mlr", "pca-quadratic", "lag-ridge")
BASE_CHOICE_RULE = (
    "the base whose residual analysis on the training runs leaves the lowest held-out RMSE "
    "there (its own leave-one-run-out); ties go to the earlier base in the list"
)
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


@dataclass(frozen=True)
class HeldOutRun:
    """One outer fold: the run held out, what the training runs chose, how it predicted."""

    run: str
    rows: int
    chosen: str
    inner_rmse_um: dict[str, float]  # each base's analysis on the training runs
    effects: dict[str, list[dict[str, Any]]]  # what each base's analysis added there
    rmse_um: dict[str, float]  # this run's held-out RMSE, per base and for the chosen one

    def as_dict(self) -> dict[str, Any]:
        return {
            "run": self.run,
            "rows": self.rows,
            "chosen_model": self.chosen,
            "inner_rmse_um": {m: round(v, 4) for m, v in self.inner_rmse_um.items()},
            "effects": self.effects,
            "rmse_um": {m: round(v, 4) for m, v in self.rmse_um.items()},
        }


@dataclass(frozen=True)
class NestedAnalysis:
    """The outer leave-one-run-out of the whole analysis (module docstring)."""

    target: str
    methods: tuple[str, ...]
    scheme: str
    runs: tuple[HeldOutRun, ...]
    measured_um: np.ndarray  # the scored rows, in outer-fold order
    predicted_um: dict[str, np.ndarray]  # per base and "chosen", aligned with measured_um

    def accuracy(self, which: str = "chosen") -> Accuracy:
        return accuracy(self.measured_um, self.predicted_um[which])

    def tables(self, tolerance_um: float | None = None) -> dict[str, Any]:
        """The figures as text cells, shared by the terminal and the HTML report."""
        chosen = self.accuracy()
        target = "" if tolerance_um is None else f" (target {tolerance_um:g} µm)"
        base_rows = [
            [m]
            + [f"{r.inner_rmse_um[m]:.2f} → {r.rmse_um[m]:.2f}" for r in self.runs]
            + [f"{self.accuracy(m).rmse_um:.2f}"]
            for m in self.methods
        ]
        return {
            "title": f"nested analysis of {self.target}: every choice made on the training "
            f"runs only, outer {self.scheme}",
            "rule": f"base in each outer fold: {BASE_CHOICE_RULE}",
            "run_header": ["held out", "chosen base", "held-out RMSE (µm)"],
            "run_rows": [[r.run, r.chosen, f"{r.rmse_um['chosen']:.2f}"] for r in self.runs],
            "headline": f"nested held-out RMSE {chosen.rmse_um:.2f} µm{target}, "
            f"max |e| {chosen.max_abs_um:.2f} µm",
            "base_note": "each base: inner RMSE (its analysis on the training runs) → held-out "
            "RMSE, µm; a base picked from the last column afterwards would be picked on the "
            "scored data",
            "base_header": ["base", *(r.run for r in self.runs), "nested alone"],
            "base_rows": base_rows if len(self.methods) > 1 else [],
        }

    def to_text(self, tolerance_um: float | None = None) -> str:
        t = self.tables(tolerance_um)
        lines = [t["title"], t["rule"], *_aligned(t["run_header"], t["run_rows"], 2), t["headline"]]
        if t["base_rows"]:
            lines += [t["base_note"], *_aligned(t["base_header"], t["base_rows"], 1)]
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {
            "target": self.target,
            "validation": f"outer {self.scheme}, every choice inside",
            "models": list(self.methods),
            "base_choice": BASE_CHOICE_RULE,
            "heldout": self.accuracy().as_dict(),
            "heldout_per_model": {m: self.accuracy(m).as_dict() for m in self.methods},
            "runs": [run.as_dict() for run in self.runs],
        }


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


def _aligned(header: Sequence[str], rows: Sequence[Sequence[str]], first_number: int) -> list[str]:
    """Indented columns, as the analysis's own tables: text left, numbers right."""
    numeric = frozenset(range(first_number, len(header)))
    lines = columns(header, [Row(tuple(r)) for r in rows], numeric)
    return ["  " + line for line in lines]
