"""What a residual analysis found: plain data, read by the CLI, the report and the store.

Kept apart from the analysis itself so that presenting a result (JSON, HTML
report, stored provenance) never needs the fitting machinery.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from models.metrics import Accuracy


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
        gain_pct: 100 × (1 − after / before) of the held-out residual about each
            fold's own mean (the shape within runs, see models.analysis).
        folds_improved: held-out folds whose RMSE went down, out of ``folds``.
        p_value: the weakest (largest) p of the partial F-test over the
            training folds, with autocorrelation-corrected degrees of freedom.
        believed: passed every rule of :mod:`models.analysis`.
        reason: why it was believed or not, in words.
        n_terms: model terms it adds.
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

    def as_dict(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "params": self.params,
            "label": self.label,
            "rmse_um": round(self.rmse_um, 4),
            "gain_pct": round(self.gain_pct, 2),
            "folds_improved": self.folds_improved,
            "folds": self.folds,
            "p_value": float(f"{self.p_value:.3g}"),
            "believed": self.believed,
            "reason": self.reason,
            "n_terms": self.n_terms,
        }


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

    def as_dict(self) -> dict[str, Any]:
        return {
            "step": self.number,
            "effect": self.effect,
            "params": self.params,
            "rmse_um": round(self.after.rmse_um, 4),
            "before": _accuracy_json(self.before),
            "after": _accuracy_json(self.after),
            "candidates": [c.as_dict() for c in self.candidates],
        }


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

    @property
    def effects(self) -> tuple[str, ...]:
        """The effects added, in order (empty when nothing was believed)."""
        return tuple(step.effect for step in self.steps if step.effect != "none")

    @property
    def effect(self) -> str:
        """The first effect added, or ``none``."""
        return self.effects[0] if self.effects else "none"

    def as_dict(self) -> dict[str, Any]:
        """The JSON of the public contract (``analyze --json``), extended."""
        added = [step for step in self.steps if step.effect != "none"]
        first_candidates = self.steps[0].candidates if self.steps else ()
        return {
            "model": self.model,
            "target": self.target,
            "sensors": list(self.sensors),
            "validation": self.validation,
            "effect": self.effect,
            "before": _accuracy_json(self.before),
            "after": _accuracy_json(self.after),
            "candidates": [c.as_dict() for c in first_candidates],
            "steps": [step.as_dict() for step in added],
            "rounds": [step.as_dict() for step in self.steps],
            "reference": self.reference,
            "rules": self.rules,
            "source": self.source,
            "data_fingerprint": self.data_fingerprint,
            "skipped_rows": self.skipped_rows,
            "stored_model": self.stored_model,
        }


def _accuracy_json(acc: Accuracy) -> dict[str, float | int]:
    return {
        "rmse_um": round(acc.rmse_um, 4),
        "sigma_um": round(acc.sigma_um, 4),
        "max_abs_um": round(acc.max_abs_um, 4),
        "n_samples": acc.n_samples,
    }
