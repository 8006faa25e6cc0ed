"""What a residual analysis found: one results object, rendered as text, HTML and JSON.

Built once by :func:`models.analysis.search.analyze`, read by the CLI, the report and the
store. Like a statsmodels results object, it holds the figures and derives every
other figure from them in one place (the properties below); its three renderers
(:func:`models.analysis.render.text_report`, :func:`models.analysis.render.html_report`,
:meth:`AnalysisResult.as_dict`) only format those properties, with the same
formatters (:mod:`models.analysis.format`), so the terminal, the page and the
JSON cannot disagree.

Two gains are reported for every candidate, named for what they are:

- ``rmse_gain_pct``: 100 × (1 − after / before) of the plain held-out RMSE, the
  figure the compensation will show on the machine;
- ``shape_gain_pct`` (the contract's ``gain_pct``): the same of the held-out
  residual about each run's own mean (the shape within runs), the figure the
  first rule of :mod:`models.analysis.search` judges, because a held-out run's constant
  offset depends on its error reference and no effect term can predict it.

The next step (:attr:`AnalysisResult.next_steps`) follows ``NEXT_STEP_RULE``.
Presenting a result never needs the fitting machinery; the HTML renderer imports
jinja2 only when called.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from models.analysis.format import (
    P_FLOOR,
    Row,
    change_text,
    columns,
    effect_name,
    p_text,
    params_text,
    pct_text,
    um_text,
)
from models.fit.metrics import Accuracy, accuracy

if TYPE_CHECKING:
    from collections.abc import Sequence

#: The held-out RMSE the compensation must reach, µm (``analyze --tolerance-um``).
DEFAULT_TOLERANCE_UM = 2.5
#: Fewer held-out runs than this are too few to prove a further effect.
MIN_RUNS_FOR_EVIDENCE = 4
#: A run holding at least this share of the held-out squared error dominates it.
DOMINANT_SHARE = 0.5
#: A run holding at least this many times its share of the rows in the held-out squared
#: error left, and at least ``OUTLIER_MIN_SHARE`` of it, is an outlier among the runs
#: (with 43 runs, one run's 22 % is 9 times its 2.3 % of the rows).
OUTLIER_FACTOR = 4.0
OUTLIER_MIN_SHARE = 0.1

NEXT_STEP_RULE = (
    "1. promote: one or more effects were added (held-out RMSE fell): save the augmented "
    "model (analyze --store) and name it in the machine's configuration. "
    "2. keep: nothing was added and the held-out RMSE is within the tolerance. "
    "3. when the final held-out RMSE is above the tolerance: more_data if the evidence is "
    f"thin (fewer than {MIN_RUNS_FOR_EVIDENCE} held-out runs, one run holding at least "
    f"{100 * DOMINANT_SHARE:g} % of the held-out squared error, or a candidate of the last "
    "round that lowered both held-out RMSEs enough but failed the fold or significance "
    "rule): record more cycles, repeating the speeds of the dominant run; otherwise, "
    f"check_run when one run holds at least {OUTLIER_FACTOR:g} times its share of the rows "
    f"in the held-out squared error and at least {100 * OUTLIER_MIN_SHARE:g} % of it: that "
    "run is an outlier (a probe, fixture or condition no other run has) to check before "
    "anything else; otherwise add_sensor: the error is spread over the runs and no candidate "
    "effect of the measured signals passes the rules, so a temperature sensor is missing "
    "where the unexplained heat flows."
)


def gain_pct(before: float, after: float) -> float:
    """100 × (1 − after / before); 0 when there is no error before."""
    return 100.0 * (1.0 - after / before) if before > 0 else 0.0


@dataclass(frozen=True)
class CandidateResult:
    """One candidate effect tried at one step, with its evidence.

    Attributes:
        effect: family name (``thermal_lag``, ``speed_direct``, ``ambient``,
            ``drift``, ``unused_sensor``, ``unsensed_heat``, …).
        params: the parameter chosen on all runs (e.g. ``{"tau_s": 1800.0}``,
            ``{"sensor": "T7"}``).
        label: short human description of the term(s) it adds.
        rmse_um: held-out RMSE with the candidate added (parameters chosen
            inside each fold on that fold's training runs only).
        gain_pct: the shape gain (see :attr:`shape_gain_pct`); the name is the
            JSON contract's.
        folds_improved: held-out folds whose residual shape improved, out of ``folds``.
        p_value: the weakest (largest) p of the partial F-test over the
            training folds, with autocorrelation-corrected degrees of freedom.
        believed: passed every rule of :mod:`models.analysis.search`.
        reason: why it was believed or not, in words.
        n_terms: model terms it adds.
        rmse_before_um: held-out RMSE of the round's model without the candidate.
        alpha: the significance level the p-value was held to (after Bonferroni).
    """

    effect: str
    params: dict[str, Any]
    label: str
    rmse_um: float
    gain_pct: float
    folds_improved: int
    folds: int
    p_value: float
    believed: bool
    reason: str
    n_terms: int
    rmse_before_um: float = math.nan
    alpha: float = math.nan

    @property
    def shape_gain_pct(self) -> float:
        """100 × (1 − after / before) of the held-out residual about each run's own mean."""
        return self.gain_pct

    @property
    def rmse_gain_pct(self) -> float:
        """100 × (1 − after / before) of the plain held-out RMSE."""
        return gain_pct(self.rmse_before_um, self.rmse_um)

    @property
    def tau_min(self) -> float | None:
        """The chosen time constant in minutes, for candidates that have one."""
        tau_s = self.params.get("tau_s")
        return None if tau_s is None else float(tau_s) / 60.0

    @property
    def p_value_reported(self) -> float:
        """The p-value floored at ``P_FLOOR`` (a p of 0 is an underflow, not a fact)."""
        return max(self.p_value, P_FLOOR) if math.isfinite(self.p_value) else self.p_value

    def as_dict(self) -> dict[str, Any]:
        record = {
            "effect": self.effect,
            "params": self.params,
            "params_text": params_text(self.params),
            "label": self.label,
            "rmse_um": round(self.rmse_um, 4),
            "rmse_before_um": _round(self.rmse_before_um, 4),
            "rmse_gain_pct": _round(self.rmse_gain_pct, 2),
            "gain_pct": round(self.gain_pct, 2),
            "shape_gain_pct": round(self.shape_gain_pct, 2),
            "folds_improved": self.folds_improved,
            "folds": self.folds,
            "p_value": float(f"{self.p_value_reported:.3g}"),
            "p_value_text": p_text(self.p_value),
            "alpha": _round(self.alpha, 6),
            "believed": self.believed,
            "reason": self.reason,
            "n_terms": self.n_terms,
        }
        if self.tau_min is not None:
            record["tau_min"] = round(self.tau_min, 3)
        return record


@dataclass(frozen=True)
class StepResult:
    """One round: every candidate tried, the one added (or none), before and after.

    ``signal`` is the chosen effect's first added term over all rows (for the
    "residual against the effect's signal" plot), ``signal_label`` its name
    and unit; both are ``None`` when nothing was added.
    """

    number: int
    effect: str  # the effect added, or "none"
    params: dict[str, Any]
    before: Accuracy
    after: Accuracy
    candidates: tuple[CandidateResult, ...]
    predicted_before_um: np.ndarray
    predicted_after_um: np.ndarray
    signal: np.ndarray | None = None
    signal_label: str | None = None

    @property
    def rmse_gain_pct(self) -> float:
        """Held-out RMSE gain of this round, 100 × (1 − after / before)."""
        return gain_pct(self.before.rmse_um, self.after.rmse_um)

    @property
    def chosen_index(self) -> int | None:
        """The candidate that was added: same effect and parameters, else same effect."""
        if self.effect == "none":
            return None
        for i, cand in enumerate(self.candidates):
            if cand.effect == self.effect and cand.params == self.params:
                return i
        for i, cand in enumerate(self.candidates):
            if cand.effect == self.effect:
                return i
        return None

    def as_dict(self) -> dict[str, Any]:
        return {
            "step": self.number,
            "effect": self.effect,
            "params": self.params,
            "params_text": params_text(self.params),
            "rmse_um": round(self.after.rmse_um, 4),
            "rmse_before_um": round(self.before.rmse_um, 4),
            "rmse_gain_pct": round(self.rmse_gain_pct, 2),
            "before": _accuracy_json(self.before),
            "after": _accuracy_json(self.after),
            "candidates": [c.as_dict() for c in self.candidates],
        }


@dataclass(frozen=True)
class RunFigures:
    """Held-out RMSE of one run before and after, and its share of the error left."""

    run: str
    n_samples: int
    rmse_before_um: float
    rmse_after_um: float
    share_after: float  # this run's part of the pooled held-out squared error after, 0…1

    def as_dict(self) -> dict[str, Any]:
        return {
            "run": self.run,
            "n_samples": self.n_samples,
            "rmse_before_um": round(self.rmse_before_um, 4),
            "rmse_after_um": round(self.rmse_after_um, 4),
            "share_of_error_after_pct": round(100.0 * self.share_after, 2),
        }


@dataclass(frozen=True)
class NextStep:
    """One recommended action: a key (``promote``, ``keep``, ``more_data``, ``check_run``,
    ``add_sensor``) and the sentence that says it."""

    action: str
    text: str


@dataclass(frozen=True)
class AnalysisResult:
    """The whole analysis: model, validation, steps, and before/after figures.

    Row-aligned arrays (``time_s``, ``run``, ``measured_um``, predictions)
    cover every analysed row; ``measured_um`` is the target as the model sees
    it (rise from its reference, µm).
    """

    model: str
    target: str
    sensors: tuple[str, ...]
    validation: str
    reference: dict[str, Any]
    rules: dict[str, Any]
    before: Accuracy
    after: Accuracy
    steps: tuple[StepResult, ...]
    time_s: np.ndarray
    run: np.ndarray
    measured_um: np.ndarray
    predicted_before_um: np.ndarray
    predicted_after_um: np.ndarray
    source: str = ""
    data_fingerprint: str = ""
    skipped_rows: str | None = None
    stored_model: dict[str, Any] | None = field(default=None)
    tolerance_um: float = DEFAULT_TOLERANCE_UM
    #: ``--model auto``: every base's held-out RMSE and the one kept (its figures above
    #: are then optimistic by that choice).
    base_choice: dict[str, Any] | None = None
    #: ``--nested``: the whole analysis scored by an outer leave-one-run-out.
    nested: NestedAnalysis | None = None
    #: the base model's forward figure (:mod:`models.fit.forward`): each later recording
    #: (or run) predicted by the base fitted on the earlier ones, against leave-one-run-out
    forward: dict[str, Any] | None = None

    # ---- figures derived once, read by every renderer ------------------------------

    @property
    def effects(self) -> tuple[str, ...]:
        """The effects added, in order (empty when nothing was believed)."""
        return tuple(step.effect for step in self.steps if step.effect != "none")

    @property
    def effect(self) -> str:
        """The first effect added, or ``none``."""
        return self.effects[0] if self.effects else "none"

    @property
    def added_steps(self) -> tuple[StepResult, ...]:
        return tuple(step for step in self.steps if step.effect != "none")

    @property
    def rmse_gain_pct(self) -> float:
        """Held-out RMSE gain of the whole analysis, 100 × (1 − after / before)."""
        return gain_pct(self.before.rmse_um, self.after.rmse_um)

    @property
    def within_tolerance(self) -> bool:
        """The final held-out RMSE is at most the tolerance."""
        return self.after.rmse_um <= self.tolerance_um

    @cached_property
    def per_run(self) -> tuple[RunFigures, ...]:
        """Held-out figures of every run, runs in order of first appearance (made once)."""
        before = self.measured_um - self.predicted_before_um
        after = self.measured_um - self.predicted_after_um
        total_after = float(after @ after)
        figures = []
        for name, rows in run_groups(self.run, self.time_s):
            sse_after = float(after[rows] @ after[rows])
            figures.append(
                RunFigures(
                    run=name,
                    n_samples=int(rows.size),
                    rmse_before_um=float(np.sqrt(np.mean(before[rows] ** 2))),
                    rmse_after_um=float(np.sqrt(sse_after / rows.size)),
                    share_after=sse_after / total_after if total_after > 0 else 0.0,
                )
            )
        return tuple(figures)

    @cached_property
    def next_steps(self) -> tuple[NextStep, ...]:
        """What to do next, by ``NEXT_STEP_RULE``."""
        steps: list[NextStep] = []
        target = f"the {um_text(self.tolerance_um)} µm tolerance"
        if self.added_steps:
            names = " + ".join(effect_name(s.effect, s.params) for s in self.added_steps)
            steps.append(
                NextStep(
                    "promote",
                    f"promote the augmented model ({self.model} + {names}): save it with "
                    "analyze --store and name it in the machine's configuration",
                )
            )
        if self.within_tolerance:
            if not steps:
                steps.append(NextStep("keep", f"keep the {self.model} model: it meets {target}"))
            return tuple(steps)
        thin = self._thin_evidence()
        outlier = self.outlier_run
        if thin:
            steps.append(NextStep("more_data", f"record more cycles: {thin}"))
        elif outlier is not None:
            rows = sum(r.n_samples for r in self.per_run)
            factor = outlier.share_after / (outlier.n_samples / rows)
            steps.append(
                NextStep(
                    "check_run",
                    f"check run {outlier.run}: it holds "
                    f"{pct_text(100.0 * outlier.share_after)} % of the held-out squared error "
                    f"left ({factor:.1f} times its share of the rows), an outlier among the "
                    f"{len(self.per_run)} runs (a probe, fixture or condition no other run "
                    f"has); the error left is above {target} and no candidate effect of the "
                    "measured signals passes the rules",
                )
            )
        else:
            steps.append(
                NextStep(
                    "add_sensor",
                    f"add a temperature sensor: the error left is above {target}, spread over "
                    "the runs, and no candidate effect of the measured signals passes the rules",
                )
            )
        return tuple(steps)

    @property
    def next_step_text(self) -> str:
        """The "what to do next" line."""
        return "; then ".join(step.text for step in self.next_steps)

    @property
    def tolerance_text(self) -> str:
        verdict = "met" if self.within_tolerance else "not met"
        return f"tolerance {um_text(self.tolerance_um)} µm: {verdict}"

    @property
    def headline(self) -> str:
        """The one sentence the reader needs if they read nothing else."""
        before, after = self.before.rmse_um, self.after.rmse_um
        added = self.added_steps
        if not added:
            return (
                f"No effect is missing: no candidate passed the rules ({self.effect}). "
                f"Held-out RMSE stays at {um_text(before)} µm; {self.tolerance_text}."
            )
        names = ", then ".join(effect_name(step.effect, step.params) for step in added)
        return (
            f"Held-out RMSE {um_text(before)} µm → {um_text(after)} µm "
            f"({change_text(self.rmse_gain_pct)} %) by adding {names}; {self.tolerance_text}."
        )

    @property
    def outlier_run(self) -> RunFigures | None:
        """The run whose part of the held-out squared error left is far above its part of
        the rows (``OUTLIER_FACTOR``, ``OUTLIER_MIN_SHARE``), or ``None``."""
        runs = self.per_run
        rows = sum(r.n_samples for r in runs)
        if len(runs) < MIN_RUNS_FOR_EVIDENCE or rows == 0:
            return None
        worst = max(runs, key=lambda r: r.share_after / r.n_samples if r.n_samples else 0.0)
        expected = worst.n_samples / rows
        if worst.share_after >= max(OUTLIER_FACTOR * expected, OUTLIER_MIN_SHARE):
            return worst
        return None

    def _thin_evidence(self) -> str | None:
        """Why the data are too thin to go further, or ``None`` (see ``NEXT_STEP_RULE``)."""
        runs = self.per_run
        if len(runs) < MIN_RUNS_FOR_EVIDENCE:
            return (
                f"only {len(runs)} run(s); {MIN_RUNS_FOR_EVIDENCE} or more are needed to prove "
                "a further effect on held-out runs"
            )
        worst = max(runs, key=lambda r: r.share_after)
        if len(runs) >= 3 and worst.share_after >= DOMINANT_SHARE:
            return (
                f"run {worst.run} holds {pct_text(100.0 * worst.share_after)} % of the held-out "
                "error; repeat its speeds so the fit sees those conditions more than once"
            )
        min_gain = float(self.rules.get("min_gain_pct", 10.0))
        last = self.steps[-1] if self.steps else None
        for cand in last.candidates if last is not None and last.effect == "none" else ():
            if cand.shape_gain_pct >= min_gain and cand.rmse_gain_pct > 0 and not cand.believed:
                return (
                    f"{effect_name(cand.effect, cand.params)} lowers the held-out RMSE "
                    f"{pct_text(cand.rmse_gain_pct)} % but is not proven ({cand.reason}); repeated "
                    "speeds would settle it"
                )
        return None

    def as_dict(self) -> dict[str, Any]:
        """The JSON of the public contract (``analyze --json``), extended."""
        first_candidates = self.steps[0].candidates if self.steps else ()
        return {
            "model": self.model,
            "target": self.target,
            "sensors": list(self.sensors),
            "validation": self.validation,
            "effect": self.effect,
            "before": _accuracy_json(self.before),
            "after": _accuracy_json(self.after),
            "rmse_gain_pct": round(self.rmse_gain_pct, 2),
            "tolerance_um": self.tolerance_um,
            "within_tolerance": self.within_tolerance,
            "headline": self.headline,
            "next_step": {
                "actions": [step.action for step in self.next_steps],
                "text": self.next_step_text,
                "rule": NEXT_STEP_RULE,
            },
            "candidates": [c.as_dict() for c in first_candidates],
            "steps": [step.as_dict() for step in self.added_steps],
            "rounds": [step.as_dict() for step in self.steps],
            "per_run": [r.as_dict() for r in self.per_run],
            "outlier_run": None if self.outlier_run is None else self.outlier_run.run,
            "reference": self.reference,
            "rules": self.rules,
            "source": self.source,
            "data_fingerprint": self.data_fingerprint,
            "skipped_rows": self.skipped_rows,
            "stored_model": self.stored_model,
        } | self._optional_json()

    def _optional_json(self) -> dict[str, Any]:
        extra: dict[str, Any] = {}
        if self.base_choice is not None:
            extra["base_choice"] = self.base_choice
        if self.nested is not None:
            extra["nested"] = self.nested.as_dict()
        if self.forward is not None:
            extra["forward"] = self.forward
        return extra


def run_groups(run: np.ndarray, time_s: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Row indices of each run, runs in order of first appearance, rows in time order.

    The order of the file is the order the engineer knows the runs by, so it is
    kept rather than sorting the names.
    """
    names = np.asarray(run).astype(str)
    unique, first, inverse = np.unique(names, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    groups = []
    for k in np.argsort(first, kind="stable"):
        rows = np.flatnonzero(inverse == k)
        rows = rows[np.argsort(time_s[rows], kind="stable")]
        groups.append((str(unique[k]), rows))
    return groups


def _round(value: float, digits: int) -> float | None:
    """Rounded, or ``None`` (JSON null) when the figure is unknown."""
    return round(value, digits) if math.isfinite(value) else None


def _accuracy_json(acc: Accuracy) -> dict[str, float | int]:
    return {
        "rmse_um": round(acc.rmse_um, 4),
        "sigma_um": round(acc.sigma_um, 4),
        "max_abs_um": round(acc.max_abs_um, 4),
        "n_samples": acc.n_samples,
    }


#: How ``--nested`` picks the base in each outer fold (:mod:`models.analysis.nested`).
BASE_CHOICE_RULE = (
    "the base whose residual analysis on the training runs leaves the lowest held-out RMSE "
    "there (its own leave-one-run-out); ties go to the earlier base in the list"
)


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


def _aligned(header: Sequence[str], rows: Sequence[Sequence[str]], first_number: int) -> list[str]:
    """Indented columns, as the analysis's own tables: text left, numbers right."""
    numeric = frozenset(range(first_number, len(header)))
    lines = columns(header, [Row(tuple(r)) for r in rows], numeric)
    return ["  " + line for line in lines]
