"""A calibrated prediction interval from the held-out residuals the fit already has.

Split-conformal: the half-width ``q`` is the ⌈(n+1)·c⌉-th smallest |held-out residual|
of the model's own validation (``c`` the nominal coverage, 0.9), so a new sample like
the held-out ones falls within ``predicted ± q`` with probability at least ``c``.

Thermal residuals are strongly autocorrelated inside a run (a model that is 4 µm off
at minute 30 is about 4 µm off at minute 31), so samples of one run are not
exchangeable with each other and a split inside a run would flatter the interval.
The residuals used are the leave-one-run-out ones (each run predicted by a model
fitted on the other runs), and the coverage stored with the calibration is checked
run by run: each run against the half-width calibrated on the *other* runs' residuals
(``per_run_coverage``), pooled as ``heldout_coverage``. That figure is on data the
calibration did not see.

A model is fitted per regime (``fit --regime-column``), and each model is validated
inside its regime, so the calibration is per regime.

The live loop widens the calibrated half-width by what a cycle lacks
(:func:`widened_um`); the gains are stored with the calibration, so the same width
is reproduced offline:

- an input outside the training span: × (1 + ``outside_gain`` · excess), the excess
  being how far beyond the span the input is, as a fraction of the span's width (the
  methods extrapolate linearly or worse, so the error grows at least in proportion);
- each machine sensor flagged bad (held, substituted by a fallback model, or lost):
  × ``bad_sensor_factor``;
- with the online correction running, the variance its estimate gained since the last
  probe, in quadrature (:func:`with_probe_age`; live only: ``score`` has no probes).

The calibration divides each held-out residual by the widening its row had against
the span of the runs its model was fitted on, so the extrapolating folds (the fastest
run held out) count as such. The gains themselves are settings, not fitted; no training
row has a held sensor, so ``bad_sensor_factor`` is not checked on data.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from functools import cache
from statistics import NormalDist
from typing import Any

import numpy as np

from models.base import ModelInputs
from models.training_range import MARGIN_FRACTION, MIN_MARGIN_C, MIN_MARGIN_RPM, training_range

#: The nominal coverage of the stored interval.
NOMINAL_COVERAGE = 0.9
#: Fewer held-out samples than this: no interval (too few to place a 90 % quantile).
MIN_SAMPLES = 30
#: Width gain per unit of excess beyond the training span (excess as a fraction of its width).
OUTSIDE_GAIN = 2.0
#: Width factor per machine sensor flagged bad.
BAD_SENSOR_FACTOR = 1.5
#: The coverage band a nominal 90 % interval is held to on data it was not calibrated on.
COVERAGE_BAND = (0.85, 0.95)


def _sorted_finite(values: np.ndarray) -> np.ndarray:
    """The finite values, smallest first: what a rank among rows is taken from."""
    array = np.asarray(values, dtype=float)
    return np.sort(array[np.isfinite(array)])


def conformal_half_width(abs_residuals_um: np.ndarray, coverage: float) -> float | None:
    """The ⌈(n+1)·coverage⌉-th smallest |residual| (µm); None when n is too small for it."""
    values = _sorted_finite(abs_residuals_um)
    n = values.size
    rank = math.ceil((n + 1) * coverage)
    if n < MIN_SAMPLES or rank > n:
        return None
    return float(values[rank - 1])


def band_half_widths(
    abs_scaled_um: np.ndarray, band: tuple[float, float] = COVERAGE_BAND
) -> list[float] | None:
    """The half-widths (µm, before any widening) that cover the band's lower and upper
    share of these rows: the ⌈n·share⌉-th smallest |residual| / widening for each.

    A stored half-width between the two would have put these rows inside the band; one
    above the upper is wider than they needed, one below the lower narrower. Comparing the
    pair of the calibration's held-out rows with the pair of a later file tells whether
    any width calibrated on the first could have been in band on the second. None
    without rows.
    """
    values = _sorted_finite(abs_scaled_um)
    if values.size == 0:
        return None
    ranks = [max(math.ceil(values.size * share), 1) for share in band]
    return [float(values[rank - 1]) for rank in ranks]


def coverage(
    measured_um: np.ndarray, predicted_um: np.ndarray, half_width_um: np.ndarray | float
) -> dict[str, float | int]:
    """Share of samples with |measured − predicted| ≤ half-width, the mean full width (µm)
    and the sample count; rows with a non-finite value or width are not counted."""
    measured = np.asarray(measured_um, dtype=float)
    predicted = np.asarray(predicted_um, dtype=float)
    width = np.broadcast_to(np.asarray(half_width_um, dtype=float), measured.shape)
    known = np.isfinite(measured) & np.isfinite(predicted) & np.isfinite(width)
    n = int(known.sum())
    if n == 0:
        return {"coverage": float("nan"), "mean_width_um": float("nan"), "n_samples": 0}
    inside = np.abs(measured[known] - predicted[known]) <= width[known]
    return {
        "coverage": float(inside.mean()),
        "mean_width_um": float(2.0 * width[known].mean()),
        "n_samples": n,
    }


def calibrate(
    measured_um: np.ndarray,
    heldout_predicted_um: np.ndarray,
    run_labels: np.ndarray,
    inputs: ModelInputs,
    nominal: float = NOMINAL_COVERAGE,
    forward_abs_residuals_um: np.ndarray | None = None,
    forward_run_labels: np.ndarray | None = None,
) -> dict[str, Any] | None:
    """The calibration stored with a model (field ``interval``), or None with too few samples.

    ``heldout_predicted_um``: each row predicted by a model that did not see its run
    (:func:`models.fit.crossval.cross_validate`); ``run_labels``: each row's run (or block);
    ``inputs``: the rows' inputs. Each residual is divided by the widening its row had
    against the span of the runs its model was fitted on, so a held-out run beyond the
    others (the fastest run, say) counts as the extrapolation it was and the width inside
    the span is not inflated by it (normalised conformal).

    ``forward_abs_residuals_um``: the |residuals| of the fit's forward figure (later runs
    predicted from earlier ones, each started as a new recording), normalised the same way
    (:func:`forward_scaled_residuals`). A plant meets its model that way, and inside one
    recording leave-one-run-out flatters the model; the stored half-width is the larger of
    the two quantiles, so it holds forward too. ``forward_run_labels`` (each forward
    residual's run) lets the stored rule itself be checked run by run
    (:func:`rule_check`).
    """
    labels = np.asarray(run_labels)
    abs_res = np.abs(np.asarray(measured_um, float) - np.asarray(heldout_predicted_um, float))
    scale = 1.0 + OUTSIDE_GAIN * _fold_excess(inputs, labels)
    q_loro = conformal_half_width(abs_res / scale, nominal)
    if q_loro is None:
        return None
    q_forward = None
    if forward_abs_residuals_um is not None:
        q_forward = conformal_half_width(forward_abs_residuals_um, nominal)
    q = stored_half_width(q_loro, q_forward)
    per_run = _per_run_coverage(abs_res, scale, labels, nominal)
    checked = [v for v in per_run.values() if v["n_samples"] > 0]
    total = sum(int(v["n_samples"]) for v in checked)
    pooled = (
        sum(float(v["coverage"]) * int(v["n_samples"]) for v in checked) / total if total else None
    )
    return {
        "method": (
            "split-conformal on leave-one-run-out residuals, normalised by the widening, "
            "and on the forward residuals: the larger half-width"
        ),
        "nominal_coverage": nominal,
        "half_width_um": q,
        "half_width_um_loro": q_loro,
        "half_width_um_forward": q_forward,
        "n_samples": int(np.isfinite(abs_res).sum()),
        "half_width_um_for_85_95": {
            "loro": band_half_widths(abs_res / scale),
            "forward": (
                band_half_widths(forward_abs_residuals_um)
                if forward_abs_residuals_um is not None
                else None
            ),
        },
        "heldout_coverage": pooled,
        "per_run_coverage": per_run,
        "stored_rule_check": rule_check(
            abs_res / scale, labels, forward_abs_residuals_um, forward_run_labels, nominal
        ),
        "outside_gain": OUTSIDE_GAIN,
        "bad_sensor_factor": BAD_SENSOR_FACTOR,
        "meaning": (
            "predicted ± half_width_um holds the measured error in nominal_coverage of samples "
            "like the held-out ones; heldout_coverage: each run checked against the width "
            "calibrated on the other runs; widened live by outside_gain per unit of excess "
            "beyond the training span and by bad_sensor_factor per sensor flagged bad; "
            "half_width_um_for_85_95: the half-widths that cover 85 % and 95 % of each "
            "scheme's held-out rows"
        ),
    }


def stored_half_width(q_loro: float, q_forward: float | None) -> float:
    """The stored half-width from the two quantiles (µm): the larger one.

    Chosen on the FL recording's first four runs only (c1–c4, channels ch1–ch5), with
    :func:`rule_check` as the criterion: of the larger quantile, the leave-one-run-out one
    alone, the pooled quantile of both residual sets, their equal-weight mixture and the
    mean of the two quantiles, the larger quantile is the one rule whose run-by-run check
    covered 85–95 % on every channel (the others fell below 85 % on one or more).
    """
    return max(q_loro, q_forward) if q_forward is not None else q_loro


def rule_check(
    loro_scaled: np.ndarray,
    loro_labels: np.ndarray,
    forward_scaled: np.ndarray | None,
    forward_labels: np.ndarray | None,
    nominal: float,
) -> dict[str, Any] | None:
    """The stored rule checked on the fit's own held-out predictions, run by run.

    Each run's held-out residuals (its leave-one-run-out ones and, where it was predicted
    forward, its forward ones; all normalised by the widening) against the half-width
    :func:`stored_half_width` gives from the *other* runs' residuals of both schemes;
    pooled per scheme and over both. None without forward residuals labelled by run.
    """
    if forward_scaled is None or forward_labels is None:
        return None
    f_res, f_lab = np.asarray(forward_scaled, float), np.asarray(forward_labels).astype(str)
    l_lab = np.asarray(loro_labels).astype(str)
    counts = np.zeros((2, 2))  # [scheme][inside, samples]
    for run in dict.fromkeys(l_lab.tolist()):
        q_loro = conformal_half_width(loro_scaled[l_lab != run], nominal)
        others = f_res[f_lab != run]
        q_fwd = conformal_half_width(others, nominal) if others.size else None
        if q_loro is None:
            continue
        q = stored_half_width(q_loro, q_fwd)
        for i, res in enumerate((loro_scaled[l_lab == run], f_res[f_lab == run])):
            res = res[np.isfinite(res)]
            counts[i] += (float((res <= q).sum()), res.size)
    if counts[:, 1].sum() == 0:
        return None

    def share(inside: float, n: float) -> float | None:
        return inside / n if n else None

    return {
        "scheme": "each run against the stored rule calibrated on the other runs' residuals",
        "leave_one_run_out": share(*counts[0]),
        "forward": share(*counts[1]),
        "both": share(*counts.sum(axis=0)),
        "n_samples": int(counts[:, 1].sum()),
    }


def forward_scaled_residuals(
    measured_um: np.ndarray,
    predicted_um: np.ndarray,
    inputs: ModelInputs,
    unit_rows: Iterable[tuple[np.ndarray, np.ndarray]],
) -> np.ndarray | None:
    """The forward figure's |residuals|, each divided by the widening its row had against
    the span of the runs its model was fitted on (as the leave-one-run-out ones are).

    ``unit_rows``: per predicted unit in order, (its rows, its model's training rows) of
    ``inputs``; None when they do not add up to the forward figure's rows.
    """
    parts = list(unit_rows)
    order = np.concatenate([rows for rows, _ in parts]) if parts else np.array([], int)
    if order.size != np.asarray(measured_um).size:
        return None
    scale = np.ones(order.size)
    at = 0
    for rows, trained in parts:
        stored = training_range(inputs.take(trained))
        for j, k in enumerate(rows):
            rises = dict(zip(inputs.sensors, map(float, inputs.rise_C[k]), strict=True))
            scale[at + j] = (
                1.0 + OUTSIDE_GAIN * span_excess(stored, rises, float(inputs.speed_rpm[k]))[0]
            )
        at += rows.size
    return np.abs(np.asarray(measured_um, float) - np.asarray(predicted_um, float)) / scale


def _fold_excess(inputs: ModelInputs, labels: np.ndarray) -> np.ndarray:
    """Each row's excess beyond the training span of the model that predicted it held out
    (the span of every other fold)."""
    excess = np.zeros(inputs.n_samples)
    for fold in dict.fromkeys(labels.tolist()):
        test = labels == fold
        stored = training_range(inputs.take(~test))
        for k in np.flatnonzero(test):
            rises = dict(zip(inputs.sensors, map(float, inputs.rise_C[k]), strict=True))
            excess[k] = span_excess(stored, rises, float(inputs.speed_rpm[k]))[0]
    return excess


def _per_run_coverage(
    abs_res: np.ndarray, scale: np.ndarray, labels: np.ndarray, nominal: float
) -> dict[str, dict[str, Any]]:
    """Each run against the (widened) half-width calibrated on every other run's residuals,
    with the half-widths that would have covered 85 % and 95 % of it."""
    found: dict[str, dict[str, Any]] = {}
    for run in dict.fromkeys(labels.tolist()):
        rows = labels == run
        q = conformal_half_width(abs_res[~rows] / scale[~rows], nominal)
        if q is None:
            continue
        known = np.isfinite(abs_res[rows])
        res, width = abs_res[rows][known], q * scale[rows][known]
        found[str(run)] = {
            "coverage": float((res <= width).mean()) if res.size else float("nan"),
            "half_width_um": q,
            "mean_width_um": float(2.0 * width.mean()) if res.size else float("nan"),
            "n_samples": int(res.size),
            "half_width_um_for_85_95": band_half_widths(res / scale[rows][known]),
        }
    return found


def excess_fraction(value: float, span: Iterable[float], min_margin: float) -> float:
    """How far ``value`` lies beyond ``span`` (with :mod:`models.training_range`'s margin),
    as a fraction of the span's width (0 inside)."""
    lo, hi = (float(v) for v in span)
    width = hi - lo
    margin = max(MARGIN_FRACTION * width, min_margin)
    beyond = max(lo - margin - value, value - hi - margin, 0.0)
    return beyond / max(width, margin)


def widened_um(calibration: dict[str, Any], excess: float, bad_sensors: int) -> float:
    """The calibrated half-width widened by the excess beyond the training span and by the
    count of sensors flagged bad (µm)."""
    q = float(calibration["half_width_um"])
    gain = float(calibration.get("outside_gain", OUTSIDE_GAIN))
    factor = float(calibration.get("bad_sensor_factor", BAD_SENSOR_FACTOR))
    return q * (1.0 + gain * max(excess, 0.0)) * factor ** max(bad_sensors, 0)


def with_probe_age(half_width_um: float, added_variance_um2: float, nominal: float) -> float:
    """The half-width widened by the online correction's variance grown since the last probe
    (µm): √(w² + z² · Δvar), z the two-sided normal quantile of ``nominal`` (1.645 at 90 %).

    The calibrated width holds the model's own residuals; the correction removes part of
    them at a probe (not counted: the width is never narrowed for it) and is then carried
    on an estimate whose variance grows as the filter's process noise says; that growth,
    independent of the model's residual, adds in quadrature.
    """
    if not added_variance_um2 > 0.0:
        return half_width_um
    z = _normal_quantile(nominal)
    return math.sqrt(half_width_um**2 + z * z * added_variance_um2)


@cache
def _normal_quantile(nominal: float) -> float:
    """z of a two-sided ``nominal`` normal interval (computed once per nominal)."""
    return float(NormalDist().inv_cdf(0.5 + nominal / 2.0))


def span_excess(
    stored: dict[str, Any], rises_C: dict[str, float], speed_rpm: float | None
) -> tuple[float, list[str]]:
    """(largest excess beyond the training span, the inputs outside it) for one sample:
    each sensor's rise (°C) by name and the speed (r/min), against ``stored``
    (:func:`models.training_range.training_range`); inputs it does not hold are skipped."""
    largest = 0.0
    names: list[str] = []
    for name, span in stored.get("rise_C", {}).items():
        value = rises_C.get(name)
        if value is None or not math.isfinite(value):
            continue
        excess = excess_fraction(value, span, MIN_MARGIN_C)
        if excess > 0.0:
            names.append(name)
            largest = max(largest, excess)
    span = stored.get("speed_rpm")
    if speed_rpm is not None and span is not None and math.isfinite(speed_rpm):
        excess = excess_fraction(abs(speed_rpm), span, MIN_MARGIN_RPM)
        if excess > 0.0:
            names.append("speed")
            largest = max(largest, excess)
    return largest, names
