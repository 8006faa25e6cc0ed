"""Ridge and lasso on the rises, the speed and their first-order lags (``--method lag-ridge``).

The growth at the tool follows the measured temperatures with delays (a part no
sensor touches, a thick casting) and follows the heat input, the speed, through
parts no sensor measures. A static map of the rises cannot follow either. This
model regresses the error on

- every sensor's rise ΔT_i and its first-order lags at the time constants
  ``lag_taus_s`` (5 min … 24 h by default);
- the speed powers n^p (n in 1000 r/min, ``speed_powers``: n, n^1.5, n², n^2.5
  by default) and their lags at the same time constants. The speed's reference
  is 0 r/min: the cold reference is taken with the spindle stopped (as the
  runtime's, :mod:`models.online.streaming`).

Which of those terms, and how they are penalised, is chosen inside ``fit`` on
the training runs alone among a small family fixed in the code
(:mod:`models.estimators.lag_structures`: a ridge with one penalty on the sensor terms and
one on the speed terms, a ridge with one penalty on every term, a lasso on the
sensors and their 30 min lags, a lasso on the sensors and the speed powers with their
30 min lags whose intercept is held at 0 µm),
by a doubly nested leave-one-run-out, each run that continues a recording scored as
the opening of a new recording carried on through the runs after it too (its cold start,
:func:`with_cold_starts`), so the choice holds
on a later file (above 10 training runs the inner folds are
5 folds of consecutive runs, :func:`models.estimators.ridge_pls.inner_groups`). The
chosen structures are stacked with weights on the simplex (a weight of 1 is one
structure alone); since every candidate's terms are among the largest one's,
the stack is one linear model on those terms. Terms are standardised on the
training rows before a penalty applies. The validation around ``fit``
therefore never lets the held-out run steer a choice.

A lag is ``x_k = a_k x_{k−1} + (1 − a_k) u_k`` with ``a_k = exp(−Δt_k / τ)``
(:func:`models.data.lag_terms.first_order_lag`; across a logging gap the exact
response to an input linear between the samples), started at the recording's first
sample and carried across the runs of one continuous recording. Inputs without
a time (``ModelInputs.time_s`` None: single rows such as the store's probe) are
taken at a steady state, every lag equal to its input; a constant sensor bias
therefore moves the prediction by the sum of that sensor's coefficients, which
is what :func:`models.fit.conditioning.bias_sensitivity` reports.

Stored as explicit JSON (no pickle): the chosen structure, the term names, the
coefficient of every term in its own unit, the standardisation (mean and scale
of every term), the penalties and the grids they came from, every candidate's
nested score and the stacking weights. :class:`LagRidgeStream` runs the
fitted model one sample at a time for the gateway's loop, carrying the lag
states (exported as plain floats, so a restarted gateway carries on warm).

Every fit is from Gram products, never a pass over the rows
(:mod:`models.estimators.lag_structures`): each run's products of the largest
candidate's terms are taken once per data set and shared by every fold and candidate
(:mod:`models.estimators.lag_grams`); per set of training runs one eigendecomposition
of the sensor block gives the ridge at every penalty and ratio, and the lasso runs on
a square root of the products (:mod:`models.estimators.lag_paths`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from models.base import ModelInputs, ThermalModel
from models.data.lag_terms import SPEED_SCALE_RPM, first_order_lag, lag_step
from models.data.references import error_origins, first_rows, reference_rows
from models.estimators.lag_grams import group_grams, inputs_fingerprint
from models.estimators.lag_structures import (
    DEFAULT_SPEED_POWERS,
    DEFAULT_TAUS_S,
    LASSO_PENALTIES,
    PENALTIES,
    SPEED_PENALTY_RATIOS,
    STACK_STEPS,
    STRUCTURE_NAMES,
    TWO_GROUP_RIDGE,
    CandidatePaths,
    GroupGrams,
    Structure,
    choose,
    ridge_path,
    standardisation,
    structure_named,
    term_groups,
)
from models.estimators.ridge_pls import inner_groups

__all__ = [
    "DEFAULT_SPEED_POWERS",
    "DEFAULT_TAUS_S",
    "GroupGrams",
    "LagRidgeModel",
    "LagRidgeStream",
    "lag_terms",
    "ridge_path",
    "standardisation",
    "term_groups",
    "term_names",
]


def term_names(
    sensors: Sequence[str], taus_s: Sequence[float], powers: Sequence[float]
) -> list[str]:
    """Names of the terms in column order: rises, speed powers, then both lagged per τ."""
    direct = [*sensors, *(speed_name(p) for p in powers)]
    return direct + [f"{name}@lag{tau:g}s" for tau in taus_s for name in direct]


def speed_name(power: float) -> str:
    if power == 0:
        return "running"
    return "n_krpm" if power == 1 else f"n_krpm^{power:g}"


def speed_powers(speed_rpm: np.ndarray, powers: Sequence[float]) -> np.ndarray:
    """(n, len(powers)) n^p with n in 1000 r/min (never negative); the power 0 is the
    running indicator, 1 while the spindle turns (n > 0) and 0 at rest, not n⁰ = 1."""
    n = np.maximum(np.asarray(speed_rpm, dtype=float), 0.0) / SPEED_SCALE_RPM
    if not powers:
        return np.empty((n.size, 0))
    return np.column_stack([(n > 0).astype(float) if p == 0 else n**p for p in powers])


#: The terms last built for one data set, by structure: validation and residual
#: analysis ask for the same inputs' terms once per fold, and the nested choice once per
#: candidate structure. The data set is the inputs object, or one with the same content
#: (a fold fitted in a worker process receives its own copy).
_last_terms: dict[tuple, np.ndarray] = {}
_last_inputs: list[ModelInputs] = []
_last_fingerprint: list[str] = []
_TERM_CACHE_SIZE = 4


def lag_terms(
    inputs: ModelInputs, sensors: Sequence[str], taus_s: Sequence[float], powers: Sequence[float]
) -> np.ndarray:
    """(n, k) terms of :func:`term_names` for ``inputs`` (steady state when it has no time).

    The last results for the same inputs object are kept (one per structure).
    """
    key = (tuple(sensors), tuple(taus_s), tuple(powers))
    if not (_last_inputs and _last_inputs[0] is inputs):
        fingerprint = inputs_fingerprint(inputs)
        if _last_fingerprint != [fingerprint]:
            _last_terms.clear()
            _last_fingerprint[:] = [fingerprint]
        _last_inputs[:] = [inputs]
    terms = _last_terms.get(key)
    if terms is None:
        terms = _build_terms(inputs, sensors, taus_s, powers)
        if len(_last_terms) >= _TERM_CACHE_SIZE:
            _last_terms.pop(next(iter(_last_terms)))
        _last_terms[key] = terms
    return terms


def _build_terms(
    inputs: ModelInputs, sensors: Sequence[str], taus_s: Sequence[float], powers: Sequence[float]
) -> np.ndarray:
    direct = np.column_stack(
        [inputs.columns(tuple(sensors)), speed_powers(inputs.speed_rpm, powers)]
    )
    if inputs.time_s is None:
        lags = [direct] * len(taus_s)  # no history: every lag has reached its input
    else:
        recording = (
            np.zeros(inputs.n_samples, dtype=int) if inputs.recording is None else inputs.recording
        )
        lags = [first_order_lag(direct, inputs.time_s, recording, tau) for tau in taus_s]
    return np.column_stack([direct, *lags])


def candidate_paths(
    inputs: ModelInputs,
    sensors: Sequence[str],
    structures: Sequence[Structure],
    y: np.ndarray,
    labels: np.ndarray,
    cold: np.ndarray | None = None,
) -> list[CandidatePaths]:
    """Each structure's terms of ``inputs`` and its fits over the groups of rows in
    ``labels`` (-1: a row left out), ready for :func:`models.estimators.lag_structures.choose`.

    The structures share the terms of the largest one (every family member's terms are
    among them) and the Gram products of its terms per run
    (:func:`models.estimators.lag_grams.group_grams`).
    """
    names = [term_names(sensors, s.lag_taus_s, s.speed_powers) for s in structures]
    largest = max(range(len(structures)), key=lambda k: len(names[k]))
    index = {name: j for j, name in enumerate(names[largest])}
    if not all(set(n) <= index.keys() for n in names):
        return [
            CandidatePaths(
                s, lag_terms(inputs, sensors, s.lag_taus_s, s.speed_powers), y, labels,
                len(sensors), n, cold=cold,
            )
            for s, n in zip(structures, names, strict=True)
        ]  # fmt: skip
    full = structures[largest]
    terms = lag_terms(inputs, sensors, full.lag_taus_s, full.speed_powers)
    key = _last_fingerprint[0] + repr((tuple(sensors), full.lag_taus_s, full.speed_powers))
    order, products = group_grams(key, terms, y, labels, inputs.run_index)
    shared: dict = {}
    paths = []
    for structure, own in zip(structures, names, strict=True):
        columns = np.array([index[name] for name in own], dtype=int)
        grams = GroupGrams.from_products(order, products, columns)
        paths.append(
            CandidatePaths(
                structure, terms, y, labels, len(sensors), own, grams, columns, shared, cold
            )
        )
    return paths


def with_cold_starts(
    inputs: ModelInputs, y: np.ndarray, labels: np.ndarray
) -> tuple[ModelInputs, np.ndarray, np.ndarray, np.ndarray | None]:
    """``inputs`` and ``y`` with the cold starts of the training runs appended: (inputs, y,
    labels, cold), the appended rows labelled −1 (never fitted on) and marked in ``cold``
    with the group of the run they copy (−1 elsewhere, and on a copied row left out).

    A cold start is a new recording opened at a training run that continues a recording,
    as a gateway meets a later file: from that run on to the end of the recording, its
    rises taken from that run's own reference rows
    (:func:`models.data.references.reference_rows`), every lag started at its first
    sample, its error from an origin of its own where its at-rest lead-in reads more than
    1 µm (:func:`models.data.references.error_origins`). The new recording is carried on
    through the runs after it, as a later file of several runs is: a lag that leans on
    the history of the one long recording (a 24 h lag) fails there, and more so in the
    second run after the start than in the first. Runs that open a recording, and runs
    with rows left out, start no copy (a copy runs through a left-out run unscored).
    """
    if inputs.run_index is None or inputs.time_s is None:
        return inputs, y, labels, None
    recording = np.zeros(inputs.n_samples, int) if inputs.recording is None else inputs.recording
    run = inputs.run_index
    opening = np.isin(run, run[first_rows(recording)])
    partial = np.isin(run, run[labels < 0])
    starts = first_rows(run)[~opening & ~partial]
    starts = np.unique(starts)
    if starts.size == 0:
        return inputs, y, labels, None
    parts: list[ModelInputs] = []
    rises, targets, colds = [], [], []
    row = np.arange(inputs.n_samples)
    for start in starts:
        copied = (recording == recording[start]) & (row >= start)
        part = inputs.take(copied)
        assert part.time_s is not None  # a mix scored on runs has its times
        one = np.zeros(part.n_samples, dtype=int)
        reference = reference_rows(one, part.time_s, part.speed_rpm)
        rises.append(part.rise_C - part.rise_C[reference].mean(axis=0))
        targets.append(y[copied] - error_origins(y[copied], one, reference, part.speed_rpm)[0])
        colds.append(labels[copied])
        parts.append(part)
    offset = int(run.max()) + 1
    first_recording = int(recording.max()) + 1
    joined = ModelInputs(
        rise_C=np.vstack([inputs.rise_C, *rises]),
        sensors=inputs.sensors,
        speed_rpm=np.concatenate([inputs.speed_rpm, *(p.speed_rpm for p in parts)]),
        run_index=np.concatenate(
            [run, *(np.asarray(p.run_index) + offset * (k + 1) for k, p in enumerate(parts))]
        ),
        time_s=np.concatenate([inputs.time_s, *(p.time_s for p in parts)]),
        recording=np.concatenate(
            [recording, *(np.full(p.n_samples, first_recording + k) for k, p in enumerate(parts))]
        ),
    )
    cold = np.concatenate([np.full(inputs.n_samples, -1), *colds])
    extra = cold.size - inputs.n_samples
    return joined, np.concatenate([y, *targets]), np.r_[labels, np.full(extra, -1)], cold


def _without_constant_speed(
    candidates: tuple[Structure, ...], speed_rpm: np.ndarray
) -> tuple[Structure, ...]:
    """``candidates`` without their speed powers when the speed does not vary on the
    training rows (not recorded, or one speed throughout): such terms are constant, the
    data say nothing of them, and a model without them does not need the speed."""
    speed = np.asarray(speed_rpm, dtype=float)
    if speed.size and np.ptp(speed) > 0:
        return candidates
    return tuple(dataclasses.replace(c, speed_powers=()) for c in candidates)


class LagRidgeModel(ThermalModel):
    """Rises, speed powers and their lags; the structure and its penalties chosen nested."""

    method = "lag-ridge"

    def __init__(
        self,
        sensors: Sequence[str] | None = None,
        lag_taus_s: Sequence[float] | None = None,
        speed_powers: Sequence[float] | None = None,
        structures: Sequence[str] | None = None,
    ) -> None:
        """``lag_taus_s`` / ``speed_powers``: one given structure (two-group ridge on those
        terms, nothing else tried); otherwise ``fit`` chooses among ``structures`` (names in
        :data:`models.estimators.lag_structures.STRUCTURES`, default every one)."""
        self.sensors = None if sensors is None else list(sensors)
        self._given_taus = None if lag_taus_s is None else [float(t) for t in lag_taus_s]
        self._given_powers = None if speed_powers is None else [float(p) for p in speed_powers]
        self._structure_names = None if structures is None else [str(n) for n in structures]
        if self._given_taus is not None or self._given_powers is not None:
            if structures is not None:
                raise ValueError("lag-ridge: give either lag_taus_s/speed_powers or structures")
            taus = DEFAULT_TAUS_S if self._given_taus is None else self._given_taus
            powers = DEFAULT_SPEED_POWERS if self._given_powers is None else self._given_powers
            given = Structure("given", tuple(taus), tuple(powers), TWO_GROUP_RIDGE)
            self.candidates: tuple[Structure, ...] = (given,)
        else:
            names = STRUCTURE_NAMES if structures is None else tuple(structures)
            if not names:
                raise ValueError("lag-ridge: structures must name at least one structure")
            self.candidates = tuple(structure_named(n) for n in names)
        self._use(self.candidates[0])

    def _use(self, structure: Structure) -> None:
        """The terms this model computes and streams are ``structure``'s."""
        self.structure_ = structure
        self.lag_taus_s = list(structure.lag_taus_s)
        self.speed_powers = list(structure.speed_powers)

    def hyperparams(self) -> dict[str, Any]:
        return {
            "sensors": self.sensors,
            "lag_taus_s": self._given_taus,
            "speed_powers": self._given_powers,
            "structures": self._structure_names,
        }

    @property
    def uses_speed(self) -> bool:
        return bool(self.speed_powers)

    # --- fitting ---------------------------------------------------------------------
    def _fit(self, inputs: ModelInputs, error_um: np.ndarray) -> None:
        self._fit_terms(inputs, error_um, None)

    def fit_rows(
        self, inputs: ModelInputs, error_um: np.ndarray, rows: np.ndarray
    ) -> LagRidgeModel:
        """Fit on ``rows``, the lags built over all of ``inputs`` (the whole history)."""
        y = np.asarray(error_um, dtype=float)
        if y.shape != (inputs.n_samples,):
            raise ValueError(f"error_um must be ({inputs.n_samples},), got {y.shape}")
        mask = np.zeros(inputs.n_samples, dtype=bool)
        mask[rows] = True
        if not np.all(np.isfinite(y[mask])) or not np.all(np.isfinite(inputs.rise_C[mask])):
            raise ValueError("fit needs finite temperatures and errors (found NaN or inf)")
        self._fit_terms(inputs, y, mask)
        return self

    def _fit_terms(self, inputs: ModelInputs, y: np.ndarray, rows: np.ndarray | None) -> None:
        from threadpoolctl import threadpool_limits

        used = tuple(self.sensors) if self.sensors is not None else inputs.sensors
        part = inputs if rows is None else inputs.take(rows)
        labels = np.full(inputs.n_samples, -1)
        labels[rows if rows is not None else slice(None)] = inner_groups(part)
        candidates = _without_constant_speed(self.candidates, part.speed_rpm)
        cold = None
        if len(candidates) > 1:
            inputs, y, labels, cold = with_cold_starts(inputs, y, labels)
        # Small dense problems: one BLAS thread is faster than several fighting for cores.
        with threadpool_limits(1):
            choice = choose(candidate_paths(inputs, used, candidates, y, labels, cold))
        self._use(choice.structure)
        self._design_cache: tuple[ModelInputs, np.ndarray] | None = None
        self.sensors_used_ = used
        self.intercept_um_ = float(choice.beta[0])
        self.coef_ = choice.beta[1:]
        self.term_mean_ = choice.mean
        self.term_scale_ = choice.scale
        self.penalties_ = choice.penalties
        self.inner_rmse_um_ = choice.inner_rmse_um
        self.cold_rmse_um_ = choice.cold_rmse_um
        self.stack_weights_ = choice.weights

    # --- prediction ------------------------------------------------------------------
    def _terms(self, inputs: ModelInputs) -> np.ndarray:
        return lag_terms(inputs, self.sensors_used_, self.lag_taus_s, self.speed_powers)

    def _predict(self, inputs: ModelInputs) -> np.ndarray:
        if inputs.time_s is None:
            # No history: every lag equals its input, so each input's coefficients add up
            # (the bias sensitivity predicts dozens of shifted copies of the training rows).
            direct = _build_terms(inputs, self.sensors_used_, (), self.speed_powers)
            summed = self.coef_.reshape(len(self.lag_taus_s) + 1, direct.shape[1]).sum(axis=0)
            return self.intercept_um_ + direct @ summed
        return self.intercept_um_ + self._terms(inputs) @ self.coef_

    def predict_rows(self, inputs: ModelInputs, rows: np.ndarray) -> np.ndarray:
        return self.predict(inputs)[rows]

    def design_matrix(self, inputs: ModelInputs) -> np.ndarray:
        """One column: the fitted prediction, µm.

        Residual analysis refits its base terms by least squares jointly with a
        candidate's; refitting this model's hundreds of terms without their
        penalties would undo the ridge, so the analysis scales the penalised
        prediction instead (coefficient ≈ 1). The last column made is kept.
        """
        cached = getattr(self, "_design_cache", None)
        if cached is not None and cached[0] is inputs:
            return cached[1]
        column = self.predict(inputs)[:, None]
        self._design_cache = (inputs, column)
        return column

    def conditioning_design(self, inputs: ModelInputs) -> tuple[np.ndarray, list[str]]:
        """Every term with its name, for the condition number and VIF of the design."""
        names = term_names(self.sensors_used_, self.lag_taus_s, self.speed_powers)
        return self._terms(inputs), names

    def input_units(self) -> dict[str, str]:
        units = {name: "°C rise" for name in self.sensors_used_}
        if self.uses_speed:
            units["speed_rpm"] = "r/min"
        units["time_s"] = "s (lag states carried from sample to sample)"
        return units

    # --- storage ---------------------------------------------------------------------
    def fitted_params(self) -> dict[str, Any]:
        names = term_names(self.sensors_used_, self.lag_taus_s, self.speed_powers)
        grid = {
            "sensors": list(PENALTIES),
            "speed_over_sensors": list(SPEED_PENALTY_RATIOS),
            "l1_over_target_sigma": list(LASSO_PENALTIES),
            "chosen_by": "leave-one-run-out on the training runs",
        }
        return {
            "structure": self.structure_.as_dict(),
            "sensors": list(self.sensors_used_),
            "lag_taus_s": list(self.lag_taus_s),
            "speed_powers": list(self.speed_powers),
            "speed_unit": "n in 1000 r/min, reference 0 r/min",
            "intercept_um": self.intercept_um_,
            "terms": names,
            "coefficients_um_per_unit": [float(b) for b in self.coef_],
            "standardisation": {
                "mean": [float(m) for m in self.term_mean_],
                "scale": [float(s) for s in self.term_scale_],
            },
            "penalties": dict(self.penalties_),
            "penalty_grid": grid,
            "structure_choice": {
                "candidates": [s.as_dict() for s in self.candidates],
                "inner_rmse_um": dict(self.inner_rmse_um_),
                "cold_start_rmse_um": dict(getattr(self, "cold_rmse_um_", {})),
                "weights": dict(self.stack_weights_),
                "weight_step": 1.0 / STACK_STEPS,
                "chosen_by": (
                    "weights on the simplex with the lowest of the worse of two mean squared "
                    "errors over the training runs, each run predicted by every structure "
                    "fitted on the other training runs with its penalty chosen on those "
                    "alone: as the recording carried it, and as a new recording (its own "
                    "cold reference, lags from its first sample) opened at each run that "
                    "continues a recording and carried on to the recording's end"
                    if self.inner_rmse_um_
                    else "the only candidate"
                ),
            },
        }

    def _load_params(self, params: dict[str, Any]) -> None:
        self.sensors_used_ = tuple(params["sensors"])
        if "structure" in params:
            self._use(Structure.from_dict(params["structure"]))
        else:  # stored before the structure was chosen: two-group ridge on its terms
            taus = tuple(float(t) for t in params["lag_taus_s"])
            powers = tuple(float(p) for p in params["speed_powers"])
            self._use(Structure("given", taus, powers, TWO_GROUP_RIDGE))
        self.intercept_um_ = float(params["intercept_um"])
        self.coef_ = np.asarray(params["coefficients_um_per_unit"], dtype=float)
        names = term_names(self.sensors_used_, self.lag_taus_s, self.speed_powers)
        if list(params["terms"]) != names or self.coef_.size != len(names):
            raise ValueError("lag-ridge: the stored terms do not match its sensors, τ and powers")
        self.term_mean_ = np.asarray(params["standardisation"]["mean"], dtype=float)
        self.term_scale_ = np.asarray(params["standardisation"]["scale"], dtype=float)
        self.penalties_ = {k: float(v) for k, v in params["penalties"].items()}
        choice = params.get("structure_choice", {})
        self.inner_rmse_um_ = {k: float(v) for k, v in choice.get("inner_rmse_um", {}).items()}
        cold = choice.get("cold_start_rmse_um", {})
        self.cold_rmse_um_ = {k: float(v) for k, v in cold.items()}
        self.stack_weights_ = {k: float(v) for k, v in choice.get("weights", {}).items()}

    def summary(self) -> str:
        taus = ", ".join(f"{t / 60:g}" for t in self.lag_taus_s)
        penalties = ", ".join(f"{k} {v:.3g}" for k, v in self.penalties_.items())
        scores = ", ".join(f"{k} {v:.2f}" for k, v in self.inner_rmse_um_.items())
        chosen = f"; inner RMSE µm {scores}" if scores else ""
        speed = f" and {len(self.speed_powers)} speed powers" if self.speed_powers else ""
        return (
            f"lag-ridge [{self.structure_.name}: {self.structure_.estimator}]: "
            f"{len(self.sensors_used_)} sensors{speed} "
            f"with lags at τ = {taus} min ({self.coef_.size} terms); penalties "
            f"{penalties} (nested leave-one-run-out{chosen})"
        )

    def stream(self) -> LagRidgeStream:
        return LagRidgeStream(self)


class LagRidgeStream:
    """A fitted :class:`LagRidgeModel` stepped one sample at a time.

    Fed the rows of one continuous recording in order it gives the batch
    predictions (the same recursion, each sample's own Δt). The first sample
    starts every lag at its input. A sample that lacks an input gives no
    prediction and leaves the states as they were.
    """

    def __init__(self, model: LagRidgeModel) -> None:
        self.model = model
        self.names = term_names(model.sensors_used_, (), model.speed_powers)
        self.reset()

    def reset(self) -> None:
        self._time_s: float | None = None
        self._lags: np.ndarray | None = None  # (τ, direct terms)
        self._last: np.ndarray | None = None  # the direct terms last stepped with

    @property
    def time_s(self) -> float | None:
        return self._time_s

    def direct(self, rises_C: Mapping[str, float], speed_rpm: float | None) -> np.ndarray | None:
        values = [rises_C.get(s) for s in self.model.sensors_used_]
        if self.model.speed_powers:
            values.append(speed_rpm)
        if any(v is None or not math.isfinite(float(v)) for v in values):
            return None
        rises = np.array([float(rises_C[s]) for s in self.model.sensors_used_])
        speed = speed_powers(np.array([float(speed_rpm or 0.0)]), self.model.speed_powers)[0]
        return np.r_[rises, speed]

    def step_terms(
        self, time_s: float, rises_C: Mapping[str, float], speed_rpm: float | None
    ) -> np.ndarray | None:
        """Advance the lags to ``time_s``; the full term vector (None if an input is missing)."""
        u = self.direct(rises_C, speed_rpm)
        if u is None:
            return None
        if self._time_s is not None and time_s < self._time_s:
            raise ValueError(f"lag-ridge: time went back: {time_s} s after {self._time_s} s")
        taus = np.asarray(self.model.lag_taus_s)[:, None]
        if self._lags is None or self._time_s is None:
            self._lags = np.tile(u, (taus.size, 1))
        else:
            self._lags = lag_step(self._lags, self._last, u, time_s - self._time_s, taus)
        self._time_s = float(time_s)
        self._last = u
        return np.r_[u, self._lags.ravel()]

    def step(
        self, time_s: float, rises_C: Mapping[str, float], speed_rpm: float | None
    ) -> float | None:
        terms = self.step_terms(time_s, rises_C, speed_rpm)
        if terms is None:
            return None
        return float(self.model.intercept_um_ + terms @ self.model.coef_)

    def state_keys(self) -> list[str]:
        return [f"{name}@lag{tau:g}s" for tau in self.model.lag_taus_s for name in self.names]

    def input_keys(self) -> list[str]:
        """Keys of the direct terms last stepped with (the start of a gap's line)."""
        return [f"{name}@input" for name in self.names]

    def export_state(self) -> dict[str, float]:
        if self._time_s is None or self._lags is None:
            return {}
        state = {"time_s": self._time_s}
        state.update(zip(self.state_keys(), map(float, self._lags.ravel()), strict=True))
        if self._last is not None:
            state.update(zip(self.input_keys(), map(float, self._last), strict=True))
        return state

    def import_state(self, state: Mapping[str, float]) -> None:
        """Carry on from :meth:`export_state`; a state saved without the last inputs
        (an earlier release) loads too, and its next step holds the new sample."""
        if not state:
            self.reset()
            return
        expected = {"time_s", *self.state_keys(), *self.input_keys()}
        if set(state) != expected and set(state) != expected - set(self.input_keys()):
            missing, unknown = sorted(expected - set(state)), sorted(set(state) - expected)
            raise ValueError(
                f"lag-ridge: state does not fit this model (missing {missing}, unknown {unknown})"
            )
        values = np.array([float(state[k]) for k in self.state_keys()])
        if not (np.all(np.isfinite(values)) and math.isfinite(float(state["time_s"]))):
            raise ValueError("lag-ridge: state holds a value that is not finite")
        self._time_s = float(state["time_s"])
        self._lags = values.reshape(len(self.model.lag_taus_s), len(self.names))
        last = [state.get(k) for k in self.input_keys()]
        self._last = None if last[0] is None else np.array(last, dtype=float)
        if self._last is not None and not np.all(np.isfinite(self._last)):
            raise ValueError("lag-ridge: state holds a value that is not finite")
