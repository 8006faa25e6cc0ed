"""Candidate effects fitted inside a lag-ridge base, judged on held-out runs.

A ``lag-ridge`` base has its sensors and speed lagged at ten time constants from
5 min to 24 h: a thermal lag, a speed-direct growth or an unsensed heat path is
among its own terms already. What it lacks is an *input*: time (a drift) or a
measured column it was not given (``ambient_C``, an unused sensor). Scaling its
penalised prediction and adding such a term beside it (the loop of
:mod:`models.analysis.search`) finds little: inside each training fit the slow
lags absorb a drift or an ambient-driven error, so the fitted residual shows
little of it, yet on a held-out run it is there (on the simulator, drift of
0.7 µm/h: 0.85 µm held out, the added drift term −1.8 %).

So each candidate input here is given to lag-ridge itself as one more input
column (its rise and its lags, penalised and chosen like the others), and the
base is refitted with it on each fold's training runs and predicts the held-out
run. A family with several variants (drift from the run's or the recording's
start) takes, in each fold, the variant whose fit scores best on that fold's
training runs alone (lag-ridge's own nested leave-one-run-out score).

The families lag-ridge holds among its own terms (``HELD_FAMILIES``: a thermal lag
of the sensors used, n and n², their lags) are given to it the same way, every
column of a variant as an input: fitted on few runs, its structure and penalty
choice can leave such an effect out. Their τ is the one the loop beside the base
chooses in each fold on that fold's training runs (one lag-ridge fit per fold, not
one per τ). A
candidate is believed by the rules of :mod:`models.analysis.search` where they
apply to held-out predictions: the shape within runs falls by at least
``MIN_GAIN_PCT`` and the plain RMSE falls; at least half the folds improve; and
the held-out residual of the base is explained by the candidate's held-out
change of the prediction (d = with − without, every row predicted by fits that
did not see its run): the F-test of r ~ 1 + d on the prewhitened rows
(Cochrane–Orcutt, ρ of r − βd within runs) gives p < ``ALPHA`` / candidates.
Under no effect d is made from other runs only, so it is unrelated to the
held-out run's own noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats
from tqdm import tqdm

from models.analysis.format import change_text, p_text
from models.analysis.result import CandidateResult, StepResult, gain_pct
from models.estimators.registry import make_model

#: A :class:`models.analysis.search.ResidualAnalysis` (not imported: the search calls this
#: module, and the import layers allow no cycle).
ResidualAnalysis = Any

if TYPE_CHECKING:
    from models.base import ModelInputs
    from models.data.lag_terms import EffectFamily, Variant

#: The families whose terms are inputs lag-ridge does not have.
INPUT_FAMILIES = ("drift", "ambient", "unused_sensor")
#: The families whose terms lag-ridge holds among its own, yet may leave out with few runs
#: (its structure and penalties chosen on them): each variant's columns (a lag of every
#: sensor used at one τ; n and n²; their lags at one τ) given to it as inputs, the τ chosen
#: in each fold by lag-ridge's own nested score, like drift's origin.
HELD_FAMILIES = ("thermal_lag", "speed_direct", "unsensed_heat")
INSIDE_COLUMN = "__effect"


@dataclass
class InsideEvaluation:
    family: EffectFamily
    predicted_um: np.ndarray
    chosen: list[int]


def input_families(analysis: ResidualAnalysis) -> list[EffectFamily]:
    """The candidate families as inputs: drift as it is, ambient as its rise (lag-ridge
    lags it itself), each unused column as its own candidate, each of them one column (its
    variant's first); a held family's variants with every column."""
    from models.data.lag_terms import EffectFamily

    families = []
    for family in analysis.families:
        if family.effect == "ambient":
            direct = tuple(v for v in family.variants if v.params.get("tau_s") == 0)
            families.append(EffectFamily(family.effect, family.label, direct[:1]))
        elif family.effect == "unused_sensor":
            families += [EffectFamily(family.effect, family.label, (v,)) for v in family.variants]
        elif family.effect in ("drift", *HELD_FAMILIES):
            families.append(family)
    one_input = [
        f if f.effect in HELD_FAMILIES
        else replace(f, variants=tuple(map(_first_column, f.variants)))
        for f in families
    ]  # fmt: skip
    return [f for f in one_input if f.variants]


def _first_column(variant: Variant) -> Variant:
    """The variant with its first column only (an input family's one input)."""
    build = variant.build
    return replace(variant, build=lambda: np.asarray(build(), dtype=float)[:, :1])


def with_input(analysis: ResidualAnalysis, variant: Variant) -> tuple[ModelInputs, list[str]]:
    """The analysis's inputs with the variant's columns (:func:`input_families`') as more
    inputs, and the sensors lag-ridge is then given (the base's own and those columns)."""
    prepared = analysis.prepared
    columns = np.asarray(variant.build(), dtype=float).reshape(prepared.data.n_samples, -1)
    names = [INSIDE_COLUMN] + [f"{INSIDE_COLUMN}{k}" for k in range(1, columns.shape[1])]
    inputs = replace(
        prepared.inputs,
        rise_C=np.column_stack([prepared.inputs.rise_C, columns]),
        sensors=(*prepared.inputs.sensors, *names),
    )
    return inputs, [*analysis.base.used_sensors, *names]


def fitted_inside_prediction(analysis: ResidualAnalysis, variant: Variant) -> np.ndarray:
    """Lag-ridge refitted with the variant's input on the analysis's rows, predicting every
    row (the rows it was not fitted on included): the model an inside step stands for."""
    inputs, sensors = with_input(analysis, variant)
    model = make_model("lag-ridge", sensors).fit_rows(inputs, analysis.y, analysis.fit_rows)
    return model.predict(inputs)


def evaluate_inside(analysis: ResidualAnalysis, family: EffectFamily) -> InsideEvaluation:
    """Held-out predictions of lag-ridge refitted with the family's input, per fold."""
    y = analysis.y
    predicted = np.zeros(y.size)
    chosen = []
    preset = _preset_choice(analysis, family)
    bar = tqdm(analysis.folds.rows, desc=f"{family.effect} inside lag-ridge", unit="fold",
               disable=not analysis.progress, leave=False, mininterval=0)  # fmt: skip
    for fold, rows in enumerate(bar):
        train = analysis.fit_rows.copy()
        train[rows] = False
        best: tuple[float, int, np.ndarray] | None = None
        offered = range(len(family.variants)) if preset is None else (preset[fold],)
        for vi in offered:
            variant = family.variants[vi]
            inputs, sensors = with_input(analysis, variant)
            model = make_model("lag-ridge", sensors).fit_rows(inputs, y, train)
            score = _inner_score(model)
            if best is None or score < best[0]:
                best = (score, vi, model.predict(inputs)[rows])
        assert best is not None
        chosen.append(best[1])
        predicted[rows] = best[2]
    return InsideEvaluation(family, predicted, chosen)


def _preset_choice(analysis: ResidualAnalysis, family: EffectFamily) -> list[int] | None:
    """Per fold, the τ of a held family with several (:data:`HELD_FAMILIES`) as the loop
    beside the base chooses it on that fold's training runs (least squares on the base's
    terms and the variant's, inner folds): one lag-ridge refit per fold instead of one per
    τ. None: each variant is refitted and lag-ridge's own nested score chooses."""
    if family.effect not in HELD_FAMILIES or len(family.variants) < 2:
        return None
    return list(analysis.evaluate([], family).chosen)


def inside_step(
    analysis: ResidualAnalysis, base_predicted: np.ndarray, alpha: float, min_gain_pct: float
) -> StepResult | None:
    """The first step judged inside lag-ridge, or ``None`` when no candidate is believed."""
    families = input_families(analysis)
    if not families:
        return None
    before = analysis._accuracy(base_predicted)
    evaluations = [evaluate_inside(analysis, family) for family in families]
    candidates = tuple(
        _judge(analysis, ev, base_predicted, before.rmse_um, alpha / len(families), min_gain_pct)
        for ev in evaluations
    )
    believed = [i for i, c in enumerate(candidates) if c.believed]
    if not believed:
        return None
    best = min(believed, key=lambda i: candidates[i].rmse_um)
    ev = evaluations[best]
    variant = ev.family.variants[_most_chosen(ev.chosen)]
    analysis.inside = variant
    return StepResult(
        1,
        ev.family.effect,
        variant.params,
        before,
        analysis._accuracy(ev.predicted_um),
        candidates,
        base_predicted,
        ev.predicted_um,
        signal=np.asarray(variant.build(), dtype=float)[:, 0],
        signal_label=variant.signal_label,
    )


def _judge(
    analysis: ResidualAnalysis,
    ev: InsideEvaluation,
    base_predicted: np.ndarray,
    before_rmse: float,
    alpha: float,
    min_gain_pct: float,
) -> CandidateResult:
    before_shape = analysis._shape_sse(base_predicted)
    after_shape = analysis._shape_sse(ev.predicted_um)
    gain = 100.0 * (1.0 - np.sqrt(after_shape.sum() / before_shape.sum()))
    after = analysis._accuracy(ev.predicted_um).rmse_um
    rmse_gain = gain_pct(before_rmse, after)
    improved = int(np.sum(after_shape < before_shape))
    count = analysis.folds.count
    p_value = heldout_p_value(analysis, base_predicted, ev.predicted_um)
    failures = []
    if gain < min_gain_pct:
        failures.append(
            f"shape within runs changes {change_text(gain)} %, needs ≤ −{min_gain_pct:g} %"
        )
    if after >= before_rmse:
        failures.append(f"held-out RMSE does not fall ({change_text(rmse_gain)} %)")
    if improved < 0.5 * count:
        failures.append(f"improves {improved}/{count} held-out folds")
    if not p_value < alpha:
        failures.append(f"p = {p_text(p_value)} ≥ {alpha:.3g} on the held-out residual")
    believed = not failures
    reason = (
        f"fitted inside lag-ridge: held-out RMSE {change_text(rmse_gain)} %, shape within "
        f"runs {change_text(gain)} %, {improved}/{count} folds better, "
        f"p = {p_text(p_value)} < {alpha:.3g}"
        if believed
        else "fitted inside lag-ridge: " + "; ".join(failures)
    )
    params: dict[str, Any] = ev.family.variants[_most_chosen(ev.chosen)].params
    return CandidateResult(
        effect=ev.family.effect,
        params=params,
        label=ev.family.label,
        rmse_um=after,
        gain_pct=gain,
        folds_improved=improved,
        folds=count,
        p_value=p_value,
        believed=believed,
        reason=reason,
        n_terms=1,
        rmse_before_um=before_rmse,
        alpha=alpha,
    )


def heldout_p_value(
    analysis: ResidualAnalysis, base_predicted: np.ndarray, with_predicted: np.ndarray
) -> float:
    """p of the F-test of r ~ 1 + d on prewhitened rows (r the base's held-out residual, d
    the candidate's held-out change of the prediction), pairs taken within folds."""
    usable = analysis.folds.index >= 0
    r = (analysis.y - base_predicted)[usable]
    d = (with_predicted - base_predicted)[usable]
    fold = analysis.folds.index[usable]
    if np.ptp(d) == 0:
        return 1.0
    slope = float(np.polyfit(d, r, 1)[0])
    rho = _lag1_within(r - slope * d, fold)
    same = fold[1:] == fold[:-1]
    rw = (r[1:] - rho * r[:-1])[same]
    dw = (d[1:] - rho * d[:-1])[same]
    z = np.column_stack([np.full(rw.size, 1.0 - rho), dw])
    beta, *_ = np.linalg.lstsq(z, rw, rcond=None)
    sse1 = float(np.sum((rw - z @ beta) ** 2))
    sse0 = float(np.sum((rw - rw.mean()) ** 2))
    df2 = rw.size - 2
    if df2 < 1 or sse1 <= 0:
        return 1.0
    statistic = max(sse0 - sse1, 0.0) / (sse1 / df2)
    return float(stats.f.sf(statistic, 1, df2))


def _lag1_within(residual: np.ndarray, fold: np.ndarray) -> float:
    """Lag-1 autocorrelation of the residual, pairs taken within folds only, in [0, 1)."""
    same = fold[1:] == fold[:-1]
    a, b = residual[1:][same], residual[:-1][same]
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return min(max(float(np.corrcoef(a, b)[0, 1]), 0.0), 0.999)


def _inner_score(model: Any) -> float:
    """The fit's own nested score on its training runs: its structures' leave-one-run-out
    RMSE weighted as they are stacked (no held-out row enters it)."""
    inner, weights = model.inner_rmse_um_, model.stack_weights_
    return float(sum(w * inner[name] for name, w in weights.items() if name in inner))


def _most_chosen(chosen: list[int]) -> int:
    values, counts = np.unique(chosen, return_counts=True)
    return int(values[np.argmax(counts)])
