"""How the sensors' rises relate to each other, learned at fit time: each one from the others.

A thermal model trusts each sensor alone. Range, rate and stuck checks judge a
sensor alone too, so a transmitter that drifts slowly, or reads a constant few
degrees high, passes them all. The sensors of one machine are not independent,
though: they sit on a few thermal bodies (bearing, shaft, motor, headstock), so
on the training data each sensor's rise is, closely, a linear function of the
others' rises. A sensor that leaves that relation is the one that is wrong.

Fitted here (numpy only) from the training rises ``X`` (n rows × p sensors, °C):

- each run's row count, mean rise μ_r (p) and covariance Σ_r (p × p, divided by
  the run's rows). From these alone, the least-squares relation of any sensor
  ``i`` on any set ``S`` of the others follows, on any set of runs, without the
  data (the runs' moments pool exactly)::

      ΔT_i ≈ a + Σ_{j∈S} b_j ΔT_j,   b = Σ_SS⁻¹ Σ_Si,   a = μ_i − b·μ_S,
      σ_in(i | S)² = Σ_ii − Σ_iS b      (the in-sample residual variance)

  so the runtime can still judge a sensor when another one is already bad;
- the *held-out* σ of every such relation: leave-one-run-out, each run
  predicted by the relation fitted on the other runs' pooled moments, its
  squared residuals summed from its own moments (n_r · ((w·μ_r − a)² + wᵀ Σ_r w)
  with w = (1 at i, −b on S)). It is the honest spread to expect on a programme
  the fit never saw: sensor lags differ, so a relation fitted on some
  programmes' dynamics misses a little on another's. With one run it is the
  in-sample σ;
- for each sensor, its relation on *all* the others (intercept, coefficients,
  in-sample and held-out σ), stated explicitly for an auditor.

The document (:meth:`SensorRelations.as_document`) is plain JSON, stored with a
model in the model store (:mod:`models.store`, field ``sensor_relations``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["RELATIONS_KIND", "RelationPrediction", "RunMoments", "SensorRelations", "fit_relations"]

RELATIONS_KIND = "linear, each sensor's rise from the others' (least squares)"

#: Relative singular-value cut-off when solving Σ_SS b = Σ_Si: sensors that are
#: (almost) copies of each other make Σ_SS nearly singular; the minimum-norm
#: solution is then used, as ``numpy.linalg.lstsq`` gives it.
RCOND = 1e-10


@dataclass(frozen=True)
class RelationPrediction:
    """What the others say about one sensor's rise (°C), and the σ to judge it by."""

    sensor: str
    predicted_rise_C: float
    sigma_C: float  # held-out σ of this very relation
    using: tuple[str, ...]
    coefficients: tuple[float, ...]  # of ``using``, °C per °C
    intercept_C: float = 0.0  # the relation's constant, included in ``predicted_rise_C``


class SensorRelations:
    """The fitted relation between a machine's sensor rises (see the module docstring)."""

    def __init__(self, sensors: Sequence[str], runs: Sequence[RunMoments]) -> None:
        names = tuple(sensors)
        if len(names) < 2 or len(set(names)) != len(names):
            raise ValueError(f"sensor relations need two or more distinct sensors, got {names}")
        if not runs:
            raise ValueError("sensor relations need the moments of at least one run")
        for k, run in enumerate(runs):
            run.check(len(names), f"per_run[{k}]")
        self.sensors = names
        self.per_run = list(runs)
        self.rows = sum(run.rows for run in runs)
        self.runs = len(runs)
        pooled = _pool(self.per_run)
        self.mean_rise_C, self.covariance_C2 = pooled.mean_rise_C, pooled.covariance_C2
        # Each fold's training moments: the other runs pooled.
        self._folds = (
            [_pool([o for j, o in enumerate(runs) if j != k]) for k in range(len(runs))]
            if len(runs) > 1
            else []
        )
        self._index = {s: k for k, s in enumerate(names)}
        # The runtime asks for the same few subsets every cycle: solve each once.
        self._solved: dict[tuple[str, tuple[str, ...]], _Relation] = {}

    # --- the relation of one sensor on a set of others --------------------------------
    def relation(self, sensor: str, using: Iterable[str]) -> tuple[float, dict[str, float], float]:
        """(intercept °C, coefficients, in-sample residual σ °C) of ``sensor`` on ``using``."""
        found = self._relation(sensor, using)
        return found.intercept_C, found.coefficients, found.sigma_in_C

    def held_out_sigma(self, sensor: str, using: Iterable[str]) -> float:
        """Leave-one-run-out residual σ (°C) of ``sensor`` on ``using`` (in-sample with one run)."""
        return self._relation(sensor, using).sigma_held_out_C

    @property
    def held_out_sigma_C(self) -> dict[str, float]:
        """Each sensor's held-out σ on all the others, °C."""
        return {s: self.held_out_sigma(s, self.sensors) for s in self.sensors}

    def _relation(self, sensor: str, using: Iterable[str]) -> _Relation:
        wanted = set(using)
        others = tuple(s for s in self.sensors if s in wanted and s != sensor)
        if not others:
            raise ValueError(f"no other sensor to relate {sensor} to")
        key = (sensor, others)
        if key not in self._solved:
            self._solved[key] = self._solve(self._index[sensor], others)
        return self._solved[key]

    def _solve(self, i: int, others: tuple[str, ...]) -> _Relation:
        idx = [self._index[s] for s in others]
        intercept, b, sigma_in = _least_squares(self.mean_rise_C, self.covariance_C2, i, idx)
        if not self._folds:
            held = sigma_in
        else:
            squared = 0.0
            for fold, run in zip(self._folds, self.per_run, strict=True):
                a_k, b_k, _ = _least_squares(fold.mean_rise_C, fold.covariance_C2, i, idx)
                w = np.zeros(len(self.sensors))
                w[i] = 1.0
                w[idx] = -b_k
                offset = float(w @ run.mean_rise_C) - a_k
                squared += run.rows * (offset**2 + float(w @ run.covariance_C2 @ w))
            held = _sqrt0(squared / self.rows)
        coefficients = dict(zip(others, (float(v) for v in b), strict=True))
        return _Relation(intercept, coefficients, sigma_in, held)

    def predict(self, sensor: str, rises_C: Mapping[str, float]) -> RelationPrediction:
        """What the other sensors in ``rises_C`` say ``sensor``'s rise is, with the held-out σ.

        ``rises_C`` may hold any subset of the fitted sensors (and others, which
        are ignored); ``sensor``'s own entry, if present, is not used.
        """
        found = self._relation(sensor, rises_C)
        predicted = found.intercept_C + sum(b * rises_C[s] for s, b in found.coefficients.items())
        return RelationPrediction(
            sensor,
            float(predicted),
            found.sigma_held_out_C,
            tuple(found.coefficients),
            tuple(found.coefficients.values()),
            found.intercept_C,
        )

    # --- JSON ---------------------------------------------------------------------------
    def as_document(self) -> dict[str, Any]:
        relations: dict[str, Any] = {}
        for sensor in self.sensors:
            found = self._relation(sensor, self.sensors)
            relations[sensor] = {
                "intercept_C": found.intercept_C,
                "coefficients_C_per_C": found.coefficients,
                "residual_sigma_C": found.sigma_in_C,
                "held_out_sigma_C": found.sigma_held_out_C,
            }
        return {
            "kind": RELATIONS_KIND,
            "sensors": list(self.sensors),
            "rows": self.rows,
            "runs": self.runs,
            "per_run": [run.as_document() for run in self.per_run],
            "relations": relations,
        }

    @classmethod
    def from_document(cls, document: Mapping[str, Any]) -> SensorRelations:
        """Rebuild from :meth:`as_document`; ValueError naming the field that is wrong."""
        try:
            runs = [RunMoments.from_document(run) for run in document["per_run"]]
            relations = cls(list(document["sensors"]), runs)
        except KeyError as exc:
            raise ValueError(f"sensor_relations: missing field {exc}") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"sensor_relations: {exc}") from None
        if document.get("rows") != relations.rows or document.get("runs") != relations.runs:
            raise ValueError("sensor_relations: 'rows'/'runs' do not match 'per_run'")
        return relations


@dataclass(frozen=True)
class RunMoments:
    """One training run's rows, mean rise (°C) and covariance of the rises (°C², over n)."""

    rows: int
    mean_rise_C: np.ndarray
    covariance_C2: np.ndarray

    @classmethod
    def of(cls, rise_C: np.ndarray) -> RunMoments:
        mean = rise_C.mean(axis=0)
        centred = rise_C - mean
        return cls(int(rise_C.shape[0]), mean, centred.T @ centred / rise_C.shape[0])

    def check(self, p: int, where: str) -> None:
        mean, cov = self.mean_rise_C, self.covariance_C2
        if self.rows < 1:
            raise ValueError(f"{where}: rows must be ≥ 1, got {self.rows}")
        if mean.shape != (p,) or cov.shape != (p, p):
            raise ValueError(
                f"{where}: mean {mean.shape} / covariance {cov.shape} do not match {p} sensors"
            )
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise ValueError(f"{where}: mean and covariance must be finite")
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12):
            raise ValueError(f"{where}: the covariance must be symmetric")

    def as_document(self) -> dict[str, Any]:
        return {
            "rows": self.rows,
            "mean_rise_C": self.mean_rise_C.tolist(),
            "covariance_C2": self.covariance_C2.tolist(),
        }

    @classmethod
    def from_document(cls, document: Mapping[str, Any]) -> RunMoments:
        return cls(
            int(document["rows"]),
            np.asarray(document["mean_rise_C"], dtype=float),
            np.asarray(document["covariance_C2"], dtype=float),
        )


@dataclass(frozen=True)
class _Relation:
    intercept_C: float
    coefficients: dict[str, float]
    sigma_in_C: float
    sigma_held_out_C: float


def _pool(runs: Sequence[RunMoments]) -> RunMoments:
    """The moments of several runs' rows together (exact, from each run's moments)."""
    rows = sum(run.rows for run in runs)
    mean = sum(run.rows * run.mean_rise_C for run in runs) / rows
    cov = sum(
        run.rows * (run.covariance_C2 + np.outer(run.mean_rise_C - mean, run.mean_rise_C - mean))
        for run in runs
    )
    return RunMoments(rows, np.asarray(mean), np.asarray(cov) / rows)


def _least_squares(
    mean: np.ndarray, cov: np.ndarray, i: int, idx: list[int]
) -> tuple[float, np.ndarray, float]:
    """(a, b, in-sample σ) of column i on columns idx, from the moments."""
    cov_si = cov[idx, i]
    b, *_ = np.linalg.lstsq(cov[np.ix_(idx, idx)], cov_si, rcond=RCOND)
    intercept = float(mean[i] - b @ mean[idx])
    return intercept, b, _sqrt0(float(cov[i, i] - cov_si @ b))


def _sqrt0(variance: float) -> float:
    """√variance, with the tiny negative round-off of an exact relation read as 0."""
    return float(np.sqrt(max(variance, 0.0)))


def fit_relations(
    rise_C: np.ndarray, sensors: Sequence[str], run_index: np.ndarray | None = None
) -> SensorRelations:
    """Fit the relations on training rises (n × p, °C); ``run_index`` labels each row's run."""
    X = np.asarray(rise_C, dtype=float)
    names = tuple(sensors)
    if X.ndim != 2 or X.shape[1] != len(names):
        raise ValueError(f"rise_C must be (n, {len(names)}), got shape {X.shape}")
    if X.shape[0] < len(names) + 1:
        raise ValueError(
            f"sensor relations need more rows ({X.shape[0]}) than sensors ({len(names)})"
        )
    if not np.all(np.isfinite(X)):
        raise ValueError("sensor relations need finite rises (found NaN or inf)")
    runs = np.zeros(X.shape[0], dtype=int) if run_index is None else np.asarray(run_index)
    labels = np.unique(runs)
    for label in labels:
        if (runs != label).sum() < len(names) and labels.size > 1:
            raise ValueError(f"run {label}: too few rows in the other runs to fit a relation")
    return SensorRelations(names, [RunMoments.of(X[runs == label]) for label in labels])
