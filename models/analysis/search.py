"""Residual analysis: which effect does the fitted model lack, and how much does adding it remove?

The loop, for one declared model (``mlr``, ``grey-mlr``, ``pca-quadratic``):

1. Fit and validate on data the fit did not see (leave-one-run-out; one run is
   cut into contiguous blocks, :func:`models.fit.crossval.fold_labels`).
2. Try every candidate family of :mod:`models.data.lag_terms`: its terms are added
   to the model's own regression terms and all coefficients are refitted
   jointly. A family's parameter (τ, sensor, origin) is chosen *inside* each
   fold by an inner leave-one-out over that fold's training runs, so the
   held-out run never steers the choice. The inner score is the residual's
   shape within each inner held-out run, as in the judging below.
3. A candidate is believed only when all of these hold (``RULES``):
   - the pooled held-out RMSE of the residual's shape within each run (about
     the run's own mean) falls by at least ``MIN_GAIN_PCT`` (10 %), and the
     plain held-out RMSE falls too. A held-out run's offset (its room level,
     its probe's zero) is what no effect can predict.
     Both gains are reported, each under its own name (``shape_gain_pct``,
     ``rmse_gain_pct``, :mod:`models.analysis.result`);
   - the held-out RMSE falls in at least ``MIN_FOLD_SHARE`` (half) of the folds;
   - on *every* training fold the partial F-test of its terms gives
     p < ``ALPHA`` / (number of families tried in that round), Bonferroni.
     Residuals of thermal data are strongly autocorrelated, so the F-test runs
     on the prewhitened regression (Cochrane–Orcutt with ρ, the lag-1
     autocorrelation of the held-out residuals). Without that correction
     every candidate would look significant on a slow signal.
   The believed candidate with the lowest held-out RMSE is added; the loop
   repeats (each family once, a lag family twice with two different time
   constants, ``unused_sensor`` once per sensor) until no candidate is
   believed or ``MAX_STEPS`` effects are in.
4. Nothing believed in the first round means the model lacks nothing this data
   can show: ``none``, and the figures after equal those before.

All the fitting is ordinary least squares from per-fold Gram matrices
(ZᵀZ, Zᵀy), so trying a candidate costs one pass over the data however many
folds and inner folds there are.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats
from tqdm import tqdm

from models.analysis.format import change_text, p_text
from models.analysis.result import AnalysisResult, CandidateResult, StepResult, gain_pct
from models.data.dataset import MeasuredRuns
from models.data.features import Prepared
from models.data.lag_terms import EffectFamily, Variant, candidate_families
from models.estimators.registry import make_model
from models.estimators.ridge_pls import grouped_runs
from models.fit.crossval import fold_labels
from models.fit.metrics import Accuracy, accuracy

MIN_GAIN_PCT = 10.0
MIN_FOLD_SHARE = 0.5
ALPHA = 0.01
MAX_STEPS = 4
LAG_FAMILIES = ("thermal_lag", "unsensed_heat", "ambient")
MAX_LAGS_PER_FAMILY = 2

RULES = {
    "min_gain_pct": MIN_GAIN_PCT,
    "min_fold_share": MIN_FOLD_SHARE,
    "alpha": ALPHA,
    "alpha_correction": "Bonferroni over the families tried in a round",
    "significance_test": (
        "partial F-test of the added terms on every training fold, on the prewhitened "
        "regression (Cochrane-Orcutt, rho = lag-1 autocorrelation of the held-out residuals)"
    ),
    "parameter_choice": (
        "inner leave-one-out on each fold's training runs, scored on the residual's shape "
        "within each inner held-out run"
    ),
    "lag_families_twice": (
        "thermal_lag, unsensed_heat, ambient may enter twice (two time constants)"
    ),
    "max_steps": MAX_STEPS,
    "heldout_figure": (
        "the analysis's own: each effect's parameter is chosen inside its folds, but its entry "
        "is judged on every fold's held-out residual, the scored one included; analyze --nested "
        "scores the whole procedure on runs no choice saw"
    ),
}


@dataclass(frozen=True)
class Folds:
    scheme: str
    index: np.ndarray  # (n,) fold number of each row
    names: tuple[str, ...]
    rows: tuple[np.ndarray, ...]  # row indices of each fold
    parts: tuple[slice | np.ndarray, ...]  # the same as slices where a fold is contiguous
    pairs: tuple[tuple[slice | np.ndarray, slice | np.ndarray], ...]  # (row t, row t−1) in a fold

    @classmethod
    def of(cls, prepared: Prepared, fit_rows: np.ndarray | None = None) -> Folds:
        """One fold per run; rows outside ``fit_rows`` (if given) belong to no fold (index −1)."""
        scheme, labels = fold_labels(prepared)
        names = tuple(dict.fromkeys(labels if fit_rows is None else labels[fit_rows]))
        number = {name: i for i, name in enumerate(names)}
        index = np.fromiter((number.get(label, -1) for label in labels), np.int32, len(labels))
        if fit_rows is not None:
            index[~fit_rows] = -1  # e.g. the rows between probes of a logged history
        rows = tuple(np.flatnonzero(index == i).astype(np.int32) for i in range(len(names)))
        parts = tuple(_as_slice(r) for r in rows)
        # Row t pairs with the fold's previous usable row: the row before it, or with a
        # target known only at probe rows, the previous probe row.
        position = np.arange(len(labels)) if fit_rows is None else np.cumsum(fit_rows) - 1
        pairs = []
        for r in rows:
            follows = np.diff(position[r]) == 1
            pairs.append((_as_slice(r[1:][follows]), _as_slice(r[:-1][follows])))
        return cls(scheme, index, names, rows, parts, tuple(pairs))

    @property
    def count(self) -> int:
        return len(self.names)


@dataclass
class Accepted:
    """An effect in the model: its family, the variant each fold chose, the overall choice."""

    family: EffectFamily
    per_fold: list[int]
    overall: int

    @property
    def params(self) -> dict[str, Any]:
        return self.family.variants[self.overall].params


@dataclass
class Evaluation:
    """Held-out result of the current model plus (optionally) one candidate family."""

    predicted_um: np.ndarray
    per_fold_sse: np.ndarray  # held-out SSE per fold
    train_sse: np.ndarray  # training SSE per fold
    train_n: np.ndarray  # training rows per fold
    chosen: list[int]  # variant index per fold
    n_columns: int  # columns of the full design (with intercept)
    n_added: int  # columns the candidate adds


class BaseDesigns:
    """The declared model's regression terms, fitted per fold (or once, when fixed)."""

    def __init__(
        self,
        method: str,
        sensors: Sequence[str] | None,
        prepared: Prepared,
        folds: Folds,
        fit_rows: np.ndarray | None = None,
        progress: bool = False,
    ):
        """``progress``: a bar over the folds fitted (on stderr)."""
        self.method = method
        self.sensors = None if sensors is None else list(sensors)
        self.prepared = prepared
        self.folds = folds
        usable = np.ones(prepared.data.n_samples, dtype=bool) if fit_rows is None else fit_rows
        probe = make_model(method, self.sensors)
        self.fixed = type(probe).fixed_design
        if self.fixed:
            self.models = [probe.fit_rows(prepared.inputs, prepared.error_um, usable)]
        else:
            self.models = []
            bar = tqdm(folds.rows, desc="base model folds", unit="fold", disable=not progress,
                       leave=False, mininterval=0)  # fmt: skip
            for rows in bar:
                train = usable.copy()
                train[rows] = False
                model = make_model(method, self.sensors)
                self.models.append(model.fit_rows(prepared.inputs, prepared.error_um, train))
        self._cache: dict[int, np.ndarray] = {}

    @property
    def used_sensors(self) -> tuple[str, ...]:
        """Sensors any fold's model uses, in input order (lag candidates build on them)."""
        used = {name for model in self.models for name in model.sensors_used_}
        return tuple(name for name in self.prepared.inputs.sensors if name in used)

    def group_of(self, fold: int) -> int:
        return 0 if self.fixed else fold

    def design(self, group: int) -> np.ndarray:
        if group not in self._cache:
            self._cache = {group: self.models[group].design_matrix(self.prepared.inputs)}
        return self._cache[group]


class ResidualAnalysis:
    """Runs the loop of the module docstring on one prepared data set."""

    def __init__(
        self,
        prepared: Prepared,
        method: str = "mlr",
        sensors: Sequence[str] | None = None,
        progress: bool = False,
        fit_rows: np.ndarray | None = None,
    ) -> None:
        self.prepared = prepared
        self.method = method
        self.y = prepared.error_um
        n = prepared.data.n_samples
        # Rows whose target the analysis may use; the others (a run held out by ``replay``)
        # still feed the effect terms' history (lags run over the whole recording).
        self.fit_rows = np.ones(n, dtype=bool) if fit_rows is None else np.asarray(fit_rows, bool)
        self.n_fit = int(self.fit_rows.sum())
        self.folds = Folds.of(prepared, None if fit_rows is None else self.fit_rows)
        self._yy = np.array([self.y[part] @ self.y[part] for part in self.folds.parts])
        self.progress = progress
        self.base = BaseDesigns(method, sensors, prepared, self.folds, fit_rows, progress)
        self.families = candidate_families(prepared, self.base.used_sensors)
        # An input effect found inside a lag-ridge base (models.analysis.inside), if any.
        self.inside: Variant | None = None

    # ---- the loop -----------------------------------------------------------------

    def run(self) -> tuple[list[StepResult], list[Accepted]]:
        accepted: list[Accepted] = []
        current = self._declared(self.evaluate(accepted, None))
        steps: list[StepResult] = []
        while len(accepted) < MAX_STEPS:
            families = self._open_families(accepted)
            if not families:
                break
            tried: list[tuple[EffectFamily, Evaluation | None]] = []
            candidates: list[CandidateResult] = []
            before = self._accuracy(current.predicted_um)
            for family in self._bar(families):
                ev = self.evaluate(accepted, family)
                candidates.append(self._judge(family, ev, current, before, accepted, len(families)))
                # Only a believed candidate can be added: the others' predictions are dropped.
                tried.append((family, ev if candidates[-1].believed else None))
            believed = [i for i, c in enumerate(candidates) if c.believed]
            if not believed:
                steps.append(
                    StepResult(
                        len(steps) + 1,
                        "none",
                        {},
                        before,
                        before,
                        tuple(candidates),
                        current.predicted_um,
                        current.predicted_um,
                    )
                )
                break
            best = min(believed, key=lambda i: candidates[i].rmse_um)
            family, believed_ev = tried[best]
            assert believed_ev is not None
            ev = believed_ev
            overall = candidates[best]
            choice = _overall_choice(ev, family)
            variant = family.variants[choice]
            accepted.append(Accepted(family, ev.chosen, choice))
            steps.append(
                StepResult(
                    len(steps) + 1,
                    family.effect,
                    overall.params,
                    before,
                    self._accuracy(ev.predicted_um),
                    tuple(candidates),
                    current.predicted_um,
                    ev.predicted_um,
                    signal=_first_column(variant),
                    signal_label=variant.signal_label,
                )
            )
            current = ev
        return steps, accepted

    def _declared(self, ev: Evaluation) -> Evaluation:
        """The base alone as ``fit`` validates it: a base refitted per fold whose design is
        not its terms (lag-ridge, ridge, pls: one column, its penalised prediction) predicts
        each held-out fold itself, not rescaled by a least-squares level and slope, so the
        analysis starts from the figure ``fit`` reports. Candidates refit that column's
        level and slope with their own terms."""
        if self.base.fixed:
            return ev  # the model is least squares on its design: the same fit
        predicted = ev.predicted_um.copy()
        for f, rows in enumerate(self.folds.rows):
            predicted[rows] = self.base.models[f].predict(self.prepared.inputs)[rows]
        sse = np.array([np.sum((self.y[rows] - predicted[rows]) ** 2) for rows in self.folds.rows])
        return dataclasses.replace(ev, predicted_um=predicted, per_fold_sse=sse)

    def _open_families(self, accepted: list[Accepted]) -> list[EffectFamily]:
        """Families that may still enter the model.

        A lag family (``LAG_FAMILIES``) may enter up to ``MAX_LAGS_PER_FAMILY``
        times, each time with a time constant not yet in: a body heated through
        two paths, or a fast and a slow part, needs two. ``unused_sensor`` keeps
        its sensors not yet added; every other family enters once.
        """
        open_: list[EffectFamily] = []
        for family in self.families:
            mine = [a for a in accepted if a.family.effect == family.effect]
            if family.effect == "unused_sensor":
                taken = {a.params["sensor"] for a in mine}
                variants = tuple(v for v in family.variants if v.params["sensor"] not in taken)
            elif family.effect in LAG_FAMILIES and len(mine) < MAX_LAGS_PER_FAMILY:
                taken_taus = {a.params["tau_s"] for a in mine}
                variants = tuple(v for v in family.variants if v.params["tau_s"] not in taken_taus)
            else:
                variants = () if mine else family.variants
            if variants:
                open_.append(EffectFamily(family.effect, family.label, variants))
        return open_

    def _accuracy(self, predicted: np.ndarray):
        return accuracy(self.y[self.fit_rows], predicted[self.fit_rows])

    def _bar(self, families: list[EffectFamily]):
        return tqdm(families, desc="candidate effects", disable=not self.progress, leave=False)

    # ---- judging --------------------------------------------------------------------

    def _judge(
        self,
        family: EffectFamily,
        ev: Evaluation,
        current: Evaluation,
        before: Accuracy,
        accepted: list[Accepted],
        n_families: int,
    ) -> CandidateResult:
        """The rules of the module docstring. ``gain`` is the shape gain (rule 1); the plain
        held-out RMSEs come from the same :func:`accuracy` as the round's before/after, so a
        candidate's figures and its step's are one number."""
        before_shape = self._shape_sse(current.predicted_um)
        after_shape = self._shape_sse(ev.predicted_um)
        after = self._accuracy(ev.predicted_um).rmse_um
        gain = 100.0 * (1.0 - np.sqrt(after_shape.sum() / before_shape.sum()))
        rmse_gain = gain_pct(before.rmse_um, after)
        improved = int(np.sum(after_shape < before_shape))
        p_value = self._p_value(family, ev, accepted)
        alpha = ALPHA / n_families
        failures = []
        if gain < MIN_GAIN_PCT:
            failures.append(
                f"shape within runs changes {change_text(gain)} %, needs ≤ −{MIN_GAIN_PCT:g} %"
            )
        if after >= before.rmse_um:
            failures.append(f"held-out RMSE does not fall ({change_text(rmse_gain)} %)")
        if improved < MIN_FOLD_SHARE * self.folds.count:
            failures.append(f"improves {improved}/{self.folds.count} held-out folds")
        if not p_value < alpha:
            failures.append(f"p = {p_text(p_value)} ≥ {alpha:.3g} on a training fold")
        believed = not failures
        reason = (
            f"held-out RMSE {change_text(rmse_gain)} %, shape within runs {change_text(gain)} %, "
            f"{improved}/{self.folds.count} folds better, p {_p_phrase(p_value)} < {alpha:.3g}"
            if believed
            else "; ".join(failures)
        )
        choice = _overall_choice(ev, family)
        return CandidateResult(
            effect=family.effect,
            params=family.variants[choice].params,
            label=family.label,
            rmse_um=after,
            gain_pct=gain,
            folds_improved=improved,
            folds=self.folds.count,
            p_value=p_value,
            believed=believed,
            reason=reason,
            n_terms=ev.n_added,
            rmse_before_um=before.rmse_um,
            alpha=alpha,
        )

    def _shape_sse(self, predicted: np.ndarray) -> np.ndarray:
        """Per fold: SSE of the held-out residual about its own mean.

        A held-out run's offset (its room level, where its probe was zeroed)
        is what no effect can predict; judging the shape of the residual
        within each run keeps a candidate from being believed for fitting
        offsets by chance.
        """
        residual = self.y - predicted
        return np.array(
            [np.sum((residual[rows] - residual[rows].mean()) ** 2) for rows in self.folds.rows]
        )

    def _p_value(self, family: EffectFamily, ev: Evaluation, accepted: list[Accepted]) -> float:
        """Largest p over the training folds of the partial F-test of the added terms.

        Thermal residuals are strongly autocorrelated, so the test is run on the
        prewhitened regression (Cochrane–Orcutt): every column and the target
        become x_t − ρ x_{t−1} within a fold, ρ the lag-1 autocorrelation of the
        held-out residuals with the candidate. On the transformed rows the
        classical F-test holds again.
        """
        rho = _lag1_autocorrelation(self.y - ev.predicted_um, self.folds.index)
        pairs = self.folds.pairs
        yy = np.array([w @ w for w in (self._whitened_y(pair, rho) for pair in pairs)])
        n_pairs = np.array([_length(now) for now, _ in pairs])
        groups: dict[tuple, list[int]] = {}
        for f in range(self.folds.count):
            key = (*self._fold_design(f, accepted), ev.chosen[f])
            groups.setdefault(key, []).append(f)
        worst = 0.0
        for key, folds_in_group in groups.items():
            fixed = self._fixed_design(key[0], accepted, key[1:-1])
            extra = family.variants[key[-1]].build()
            width = fixed.width + extra.shape[1]
            gram = np.empty((self.folds.count, width, width))
            cross = np.empty((self.folds.count, width))
            for f, (now, before) in enumerate(pairs):
                # z = [fixed, extra]; only this fold's rows of it are ever made
                z_w = fixed.joined(extra, now)
                lagged = fixed.joined(extra, before)
                lagged *= rho
                z_w -= lagged
                del lagged
                gram[f], cross[f] = z_w.T @ z_w, z_w.T @ self._whitened_y(pairs[f], rho)
            del extra
            k0 = width - ev.n_added
            for f in folds_in_group:
                g, c, t = gram.sum(0) - gram[f], cross.sum(0) - cross[f], yy.sum() - yy[f]
                sse1 = _sse(g, c, t, np.linalg.lstsq(g, c, rcond=1e-12)[0])
                g0, c0 = g[:k0, :k0], c[:k0]
                sse0 = _sse(g0, c0, t, np.linalg.lstsq(g0, c0, rcond=1e-12)[0])
                df2 = int(n_pairs.sum() - n_pairs[f]) - width
                if df2 < 1 or sse1 <= 0 or ev.n_added == 0:
                    return 1.0
                statistic = max(sse0 - sse1, 0.0) / ev.n_added / (sse1 / df2)
                worst = max(worst, float(stats.f.sf(statistic, ev.n_added, df2)))
        return worst

    def _whitened_y(self, pair: tuple[slice | np.ndarray, slice | np.ndarray], rho: float):
        """y_t − ρ y_{t−1} over one fold's pairs (made when needed, never kept for all folds)."""
        now, before = pair
        return self.y[now] - rho * self.y[before]

    # ---- fitting from Gram matrices --------------------------------------------------

    def evaluate(self, accepted: list[Accepted], family: EffectFamily | None) -> Evaluation:
        """Held-out predictions of the model with ``accepted`` effects (+ ``family``)."""
        k = self.folds.count
        variants: tuple[Variant | None, ...] = family.variants if family else (None,)
        n_variants = len(variants)
        heldout = np.full((n_variants, k), np.inf)
        inner = np.full((n_variants, k), np.inf)
        train = np.zeros((n_variants, k))
        betas: dict[tuple[int, int], np.ndarray] = {}  # (variant, fold) → coefficients
        n_columns = n_added = 0
        groups = self._fold_groups(accepted)
        designs: dict[tuple, FixedDesign] = {}
        last_built: dict[tuple, tuple[int, np.ndarray]] = {}
        # Each fold group's fixed products first, then each variant's terms made once for
        # every group (a base refitted per fold has one group per run: making the lags
        # per group and variant cost runs × rows).
        built: dict[tuple[int, int], np.ndarray] = {}  # accepted effects' terms, made once
        fixed_products = {}
        for key in groups:
            fixed = designs[key] = self._fixed_design(key[0], accepted, key[1:], built)
            fixed_products[key] = (self._grams(fixed, fixed), self._grams(fixed, self.y))
        yy = self._yy
        for vi, variant in enumerate(variants):
            last_built.clear()  # one variant's terms in memory at a time
            extra = self._extra(variant)
            for key, folds_in_group in groups.items():
                fixed = designs[key]
                n_columns, n_added = fixed.width + extra.shape[1], extra.shape[1]
                gram, cross = self._joined(fixed, extra, *fixed_products[key])
                for f in folds_in_group:
                    beta = betas[vi, f] = _solve(gram, cross, exclude=[f])
                    heldout[vi, f] = _sse(gram[f], cross[f], yy[f], beta)
                    train[vi, f] = _sse(
                        gram.sum(0) - gram[f], cross.sum(0) - cross[f], yy.sum() - yy[f], beta
                    )
                    if n_variants > 1:
                        inner[vi, f] = _inner_shape_sse(gram, cross, yy, f)
                last_built[key] = (vi, extra)
            del extra
        if family is not None:
            for f, vi in _taken_in_fold(family, accepted, k):
                inner[vi, f] = np.inf  # that fold already has this time constant in
        chosen = [int(np.argmin(inner[:, f])) if n_variants > 1 else 0 for f in range(k)]
        result = self._chosen_predictions(groups, designs, last_built, variants, chosen, betas)
        del last_built
        return Evaluation(
            predicted_um=result,
            per_fold_sse=np.array([heldout[vi, f] for f, vi in enumerate(chosen)]),
            train_sse=np.array([train[vi, f] for f, vi in enumerate(chosen)]),
            train_n=np.array([self.n_fit - rows.size for rows in self.folds.rows]),
            chosen=chosen,
            n_columns=n_columns,
            n_added=n_added,
        )

    def _fold_groups(self, accepted: list[Accepted]) -> dict[tuple, list[int]]:
        """The folds by design key: folds in one group share one design matrix."""
        groups: dict[tuple, list[int]] = {}
        for f in range(self.folds.count):
            groups.setdefault(self._fold_design(f, accepted), []).append(f)
        return groups

    def _chosen_predictions(
        self,
        groups: dict[tuple, list[int]],
        designs: dict[tuple, FixedDesign],
        last_built: dict[tuple, tuple[int, np.ndarray]],
        variants: tuple[Variant | None, ...],
        chosen: list[int],
        betas: dict[tuple[int, int], np.ndarray],
    ) -> np.ndarray:
        """Held-out predictions of the chosen variants only (a variant's terms are made
        again if another one was made after it): never one row set per variant."""
        result = np.zeros(self.y.size)  # rows outside every fold stay 0
        for key, folds_in_group in groups.items():
            fixed = designs[key]
            for vi in sorted({chosen[f] for f in folds_in_group}):
                built_vi, extra = last_built.pop(key, (None, None))
                if built_vi != vi or extra is None:
                    extra = None  # another variant's terms go before these are made
                    extra = self._extra(variants[vi])
                for f in (f for f in folds_in_group if chosen[f] == vi):
                    part, beta = self.folds.parts[f], betas[vi, f]
                    predicted = fixed.rows(part) @ beta[: fixed.width]
                    predicted += extra[part] @ beta[fixed.width :]
                    result[self.folds.rows[f]] = predicted
                del extra
        return result

    def _fold_design(self, fold: int, accepted: list[Accepted]) -> tuple[int, ...]:
        """What fixes a fold's design: its base-model group and each accepted effect's variant
        (folds with the same key share one design matrix)."""
        return (self.base.group_of(fold), *(a.per_fold[fold] for a in accepted))

    def _fixed_design(
        self,
        base_group: int,
        accepted: list[Accepted],
        choices: Sequence[int],
        built: dict[tuple[int, int], np.ndarray] | None = None,
    ) -> FixedDesign:
        """Intercept, the model's own terms and the accepted effects (each fold's variant).

        ``built`` keeps each (accepted effect, variant)'s terms for the designs of the
        other fold groups, so they are made once and shared."""
        built = {} if built is None else built
        blocks = []
        for i, (a, v) in enumerate(zip(accepted, choices, strict=True)):
            if (i, v) not in built:
                built[i, v] = a.family.variants[v].build()
            blocks.append(built[i, v])
        return FixedDesign(self.base.design(base_group), blocks)

    def _extra(self, variant: Variant | None) -> np.ndarray:
        return variant.build() if variant is not None else np.empty((self.y.size, 0))

    def _grams(self, a: FixedDesign | np.ndarray, b: FixedDesign | np.ndarray) -> np.ndarray:
        """Per fold: aᵀb (fold rows as views where the fold is contiguous; a fixed design's
        rows are made once per fold, also when ``b`` is ``a``)."""
        products = []
        for part in self.folds.parts:
            rows = a.rows(part) if isinstance(a, FixedDesign) else a[part]
            other = rows if b is a else (b.rows(part) if isinstance(b, FixedDesign) else b[part])
            products.append(rows.T @ other)
        return np.stack(products)

    def _joined(
        self,
        fixed: FixedDesign,
        extra: np.ndarray,
        fixed_gram: np.ndarray,
        fixed_cross: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-fold ZᵀZ and Zᵀy of Z = [fixed, extra], reusing the fixed block's products:
        a candidate costs only its own columns' products, not a new design matrix."""
        fixed_extra = np.stack([fixed.rows(part).T @ extra[part] for part in self.folds.parts])
        gram = np.concatenate(
            [
                np.concatenate([fixed_gram, fixed_extra], axis=2),
                np.concatenate([fixed_extra.transpose(0, 2, 1), self._grams(extra, extra)], axis=2),
            ],
            axis=1,
        )
        cross = np.concatenate([fixed_cross, self._grams(extra, self.y)], axis=1)
        return gram, cross


class FixedDesign:
    """The columns every candidate is added to: intercept, the model's own terms, and the
    effects already in (each fold's variant).

    Its rows are made one fold at a time (:meth:`rows`), so the whole (n, k) matrix
    never exists: on a million-row file it would be hundreds of megabytes. A
    fold's rows are the same numbers, in the same C order, as the slice of the
    full matrix would be, so every product is exactly what it was.
    """

    def __init__(self, base: np.ndarray, blocks: list[np.ndarray]) -> None:
        self.base = base
        self.blocks = blocks
        self.width = 1 + base.shape[1] + sum(block.shape[1] for block in blocks)

    def rows(self, part: slice | np.ndarray) -> np.ndarray:
        base = self.base[part]
        ones = np.ones((base.shape[0], 1))
        return np.column_stack([ones, base, *(block[part] for block in self.blocks)])

    def joined(self, extra: np.ndarray, part: slice | np.ndarray) -> np.ndarray:
        """Rows ``part`` of [fixed, extra]."""
        base = self.base[part]
        ones = np.ones((base.shape[0], 1))
        return np.column_stack([ones, base, *(b[part] for b in self.blocks), extra[part]])


def _solve(gram: np.ndarray, cross: np.ndarray, exclude: list[int]) -> np.ndarray:
    """Least-squares coefficients on every fold but ``exclude``, from the Gram sums."""
    g = gram.sum(0) - gram[exclude].sum(0)
    c = cross.sum(0) - cross[exclude].sum(0)
    beta, *_ = np.linalg.lstsq(g, c, rcond=1e-12)
    return beta


def _sse(gram: np.ndarray, cross: np.ndarray, yy: float, beta: np.ndarray) -> float:
    return float(max(yy - 2.0 * beta @ cross + beta @ gram @ beta, 0.0))


def _shape_sse(gram: np.ndarray, cross: np.ndarray, yy: float, beta: np.ndarray) -> float:
    """SSE of one fold's residual about its own mean (column 0 of the design is the intercept,
    so ``gram[0]`` holds the column sums and ``cross[0]`` the sum of y)."""
    mean_residual = (cross[0] - gram[0] @ beta) / gram[0, 0]
    return max(_sse(gram, cross, yy, beta) - gram[0, 0] * mean_residual**2, 0.0)


def _inner_shape_sse(gram: np.ndarray, cross: np.ndarray, yy: np.ndarray, fold: int) -> float:
    """Shape SSE of every fold but ``fold``, each predicted without itself and ``fold``.

    Up to ``INNER_GROUPED_ABOVE_RUNS`` other folds each is left out alone; above,
    ``INNER_FOLDS`` groups of consecutive folds are (runs² solves would not scale)."""
    others = np.array([s for s in range(gram.shape[0]) if s != fold])
    groups = grouped_runs(others)
    total = 0.0
    for group in np.unique(groups):
        left_out = [int(s) for s in others[groups == group]]
        beta = _solve(gram, cross, exclude=[fold, *left_out])
        total += sum(_shape_sse(gram[s], cross[s], yy[s], beta) for s in left_out)
    return total


def _length(part: slice | np.ndarray) -> int:
    return part.stop - part.start if isinstance(part, slice) else int(part.size)


def _as_slice(rows: np.ndarray) -> slice | np.ndarray:
    """A slice (a view, no copy) when ``rows`` are consecutive, else the indices themselves."""
    if rows.size and rows[-1] - rows[0] + 1 == rows.size:
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


def _taken_in_fold(family: EffectFamily, accepted: list[Accepted], k: int) -> list[tuple[int, int]]:
    """(fold, variant) pairs of ``family`` that a fold already chose for an earlier entry
    of the same family: a second lag must have another time constant in every fold."""
    taken = []
    for a in accepted:
        if a.family.effect != family.effect:
            continue
        for f in range(k):
            params = a.family.variants[a.per_fold[f]].params
            taken += [(f, vi) for vi, v in enumerate(family.variants) if v.params == params]
    return taken


def _overall_choice(ev: Evaluation, family: EffectFamily) -> int:
    """The variant most folds chose (ties: the first in the family's grid)."""
    counts = Counter(ev.chosen)
    top = max(counts.values())
    return min(v for v, c in counts.items() if c == top)


def _first_column(variant: Variant) -> np.ndarray:
    return np.asarray(variant.build(), dtype=float)[:, 0]


def _p_phrase(p_value: float) -> str:
    """``= 1.2e-05`` or ``< 1e-16``, to read after a "p"."""
    text = p_text(p_value)
    return text if text.startswith("<") else f"= {text}"


def _lag1_autocorrelation(residual: np.ndarray, fold_index: np.ndarray) -> float:
    """Lag-1 autocorrelation of the residual, pairs taken within folds only, in [0, 1)."""
    usable = fold_index >= 0  # rows outside every fold (no target there) are passed over
    residual, fold_index = residual[usable], fold_index[usable]
    same = fold_index[1:] == fold_index[:-1]
    a, b = residual[1:][same], residual[:-1][same]
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    rho = float(np.corrcoef(a, b)[0, 1])
    return min(max(rho, 0.0), 0.999)


def _refuse_constant_error(data: MeasuredRuns, fit_rows: np.ndarray | None) -> None:
    """An error column that never changes within a run has no thermal error to explain:
    every effect's shape gain would be 0/0. Refused with one line instead."""
    known = np.zeros(len(data.error_um), dtype=bool)
    known[fit_rows if fit_rows is not None else slice(None)] = True
    known &= np.isfinite(data.error_um)
    for _, rows in data.run_slices():
        values = data.error_um[rows][known[rows]]
        if values.size > 1 and np.ptp(values) > 0:
            return
    raise ValueError(
        f"{data.source}: column '{data.target}' does not change within any run: there is "
        "no thermal error to analyse (is it the measured error, see --target?)"
    )


def _inside_or_run(analysis: ResidualAnalysis) -> tuple[list[StepResult], list[Accepted]]:
    """On a lag-ridge base, the input effects refitted inside it first
    (:mod:`models.analysis.inside`); the loop of this module when none is believed.

    An effect found inside lag-ridge is part of the refitted base, not a term beside it:
    it is returned with no :class:`Accepted` (nothing to add to the scaled prediction)."""
    if analysis.method == "lag-ridge":
        from models.analysis.inside import inside_step

        base = analysis.evaluate([], None).predicted_um
        step = inside_step(analysis, base, ALPHA, MIN_GAIN_PCT)
        if step is not None:
            return [step], []
    return analysis.run()


def analyze(
    prepared: Prepared,
    method: str = "mlr",
    sensors: Sequence[str] | None = None,
    progress: bool = False,
    fit_rows: np.ndarray | None = None,
) -> tuple[AnalysisResult, list[Accepted], ResidualAnalysis]:
    """Run the residual analysis; return the result, the effects added and the analysis.

    ``fit_rows``: the rows whose target is known (e.g. probe rows of a logged history);
    the effect terms still run over every row."""
    _refuse_constant_error(prepared.data, fit_rows)
    analysis = ResidualAnalysis(prepared, method, sensors, progress, fit_rows)
    steps, accepted = _inside_or_run(analysis)
    first = steps[0]
    last = steps[-1]
    return (
        AnalysisResult(
            model=method,
            target=prepared.data.target,
            sensors=tuple(sensors) if sensors is not None else prepared.inputs.sensors,
            validation=analysis.folds.scheme,
            reference=prepared.plan.describe(),
            rules=RULES,
            before=first.before,
            after=last.after,
            steps=tuple(steps),
            time_s=prepared.data.time_s,
            run=prepared.data.run,
            measured_um=prepared.error_um,
            predicted_before_um=first.predicted_before_um,
            predicted_after_um=last.predicted_after_um,
            source=prepared.data.source,
        ),
        accepted,
        analysis,
    )
