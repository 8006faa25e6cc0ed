"""How the sensors' rises relate to each other, learned at fit time: each one from the others.

A thermal model trusts each sensor alone. Range, rate and stuck checks judge a
sensor alone too, so a transmitter that drifts slowly, or reads a constant few
degrees high, passes them all. The sensors of one machine are not independent,
though: they sit on a few thermal bodies (bearing, shaft, motor, headstock), so
on the training data each sensor's rise is, closely, a linear function of the
others' rises. A sensor that leaves that relation is the one that is wrong.

Fitted here (numpy only) from the training rises ``X`` (n rows × p sensors, °C):

- the mean rise ``mean_rise_C`` (p) and the covariance ``covariance_C2`` (p × p,
  divided by n) of the rises. From these two, the least-squares relation of any
  sensor ``i`` on any set ``S`` of the others follows without the data::

      ΔT_i ≈ a + Σ_{j∈S} b_j ΔT_j,   b = Σ_SS⁻¹ Σ_Si,   a = μ_i − b·μ_S,
      σ_in(i | S)² = Σ_ii − Σ_iS b      (the in-sample residual variance)

  so the runtime can still judge a sensor when another one is already bad;
- for each sensor, its relation on *all* the others (intercept, coefficients),
  stated explicitly for an auditor, with its in-sample residual σ and its
  *held-out* residual σ: leave-one-run-out, each run predicted by the relation
  fitted on the other runs. The held-out σ is the honest spread to expect on a
  programme the fit never saw (sensor lags differ, so a relation fitted on one
  programme's dynamics misses a little on another's).

The σ the runtime compares a residual with (:meth:`SensorRelations.predict`) is
the held-out σ, scaled by how much the in-sample σ grows when some of the other
sensors cannot be used: ``σ = σ_held-out(i) · σ_in(i | S) / σ_in(i | all others)``.

The document (:meth:`SensorRelations.as_document`) is plain JSON, stored with a
model in the model store (:mod:`models.store`, field ``sensor_relations``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["RELATIONS_KIND", "RelationPrediction", "SensorRelations", "fit_relations"]

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
    sigma_C: float
    using: tuple[str, ...]


class SensorRelations:
    """The fitted relation between a machine's sensor rises (see the module docstring)."""

    def __init__(
        self,
        sensors: Sequence[str],
        mean_rise_C: np.ndarray,
        covariance_C2: np.ndarray,
        held_out_sigma_C: Mapping[str, float],
        rows: int,
        runs: int,
    ) -> None:
        names = tuple(sensors)
        if len(names) < 2 or len(set(names)) != len(names):
            raise ValueError(f"sensor relations need two or more distinct sensors, got {names}")
        mean = np.asarray(mean_rise_C, dtype=float)
        cov = np.asarray(covariance_C2, dtype=float)
        if mean.shape != (len(names),) or cov.shape != (len(names), len(names)):
            raise ValueError(
                f"sensor relations: mean {mean.shape} / covariance {cov.shape} do not match "
                f"{len(names)} sensors"
            )
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise ValueError("sensor relations: mean and covariance must be finite")
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12):
            raise ValueError("sensor relations: the covariance must be symmetric")
        missing = [s for s in names if s not in held_out_sigma_C]
        if missing:
            raise ValueError(f"sensor relations: no held-out σ for {missing}")
        held = {s: float(held_out_sigma_C[s]) for s in names}
        if not all(np.isfinite(v) and v >= 0 for v in held.values()):
            raise ValueError(f"sensor relations: held-out σ must be finite and ≥ 0, got {held}")
        self.sensors = names
        self.mean_rise_C = mean
        self.covariance_C2 = cov
        self.held_out_sigma_C = held
        self.rows = int(rows)
        self.runs = int(runs)
        self._index = {s: k for k, s in enumerate(names)}
        # The runtime asks for the same few subsets every cycle: solve each once.
        self._solved: dict[tuple[str, tuple[str, ...]], tuple[float, dict[str, float], float]] = {}

    # --- the relation of one sensor on a set of others --------------------------------
    def relation(self, sensor: str, using: Iterable[str]) -> tuple[float, dict[str, float], float]:
        """(intercept °C, coefficients, in-sample residual σ °C) of ``sensor`` on ``using``."""
        i = self._index[sensor]
        wanted = set(using)
        others = [s for s in self.sensors if s in wanted and s != sensor]
        if not others:
            raise ValueError(f"no other sensor to relate {sensor} to")
        key = (sensor, tuple(others))
        if key not in self._solved:
            self._solved[key] = self._solve(i, others)
        return self._solved[key]

    def _solve(self, i: int, others: list[str]) -> tuple[float, dict[str, float], float]:
        idx = [self._index[s] for s in others]
        cov_ss = self.covariance_C2[np.ix_(idx, idx)]
        cov_si = self.covariance_C2[idx, i]
        b, *_ = np.linalg.lstsq(cov_ss, cov_si, rcond=RCOND)
        intercept = float(self.mean_rise_C[i] - b @ self.mean_rise_C[idx])
        variance = float(self.covariance_C2[i, i] - cov_si @ b)
        return intercept, dict(zip(others, (float(v) for v in b), strict=True)), _sqrt0(variance)

    def predict(self, sensor: str, rises_C: Mapping[str, float]) -> RelationPrediction:
        """What the other sensors in ``rises_C`` say ``sensor``'s rise is.

        ``rises_C`` may hold any subset of the fitted sensors (and others, which
        are ignored); ``sensor``'s own entry, if present, is not used.
        """
        using = tuple(s for s in self.sensors if s in rises_C and s != sensor)
        intercept, coefficients, sigma_in = self.relation(sensor, using)
        predicted = intercept + sum(b * rises_C[s] for s, b in coefficients.items())
        _, _, sigma_all = self.relation(sensor, self.sensors)
        held = self.held_out_sigma_C[sensor]
        sigma = held * sigma_in / sigma_all if sigma_all > 0 else max(held, sigma_in)
        return RelationPrediction(sensor, float(predicted), float(sigma), using)

    # --- JSON ---------------------------------------------------------------------------
    def as_document(self) -> dict[str, Any]:
        relations: dict[str, Any] = {}
        for sensor in self.sensors:
            intercept, coefficients, sigma_in = self.relation(sensor, self.sensors)
            relations[sensor] = {
                "intercept_C": intercept,
                "coefficients_C_per_C": coefficients,
                "residual_sigma_C": sigma_in,
                "held_out_sigma_C": self.held_out_sigma_C[sensor],
            }
        return {
            "kind": RELATIONS_KIND,
            "sensors": list(self.sensors),
            "rows": self.rows,
            "runs": self.runs,
            "mean_rise_C": self.mean_rise_C.tolist(),
            "covariance_C2": self.covariance_C2.tolist(),
            "relations": relations,
        }

    @classmethod
    def from_document(cls, document: Mapping[str, Any]) -> SensorRelations:
        """Rebuild from :meth:`as_document`; ValueError naming the field that is wrong."""
        try:
            relations = document["relations"]
            held = {s: float(relations[s]["held_out_sigma_C"]) for s in document["sensors"]}
            return cls(
                sensors=list(document["sensors"]),
                mean_rise_C=np.asarray(document["mean_rise_C"], dtype=float),
                covariance_C2=np.asarray(document["covariance_C2"], dtype=float),
                held_out_sigma_C=held,
                rows=int(document["rows"]),
                runs=int(document["runs"]),
            )
        except KeyError as exc:
            raise ValueError(f"sensor_relations: missing field {exc}") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"sensor_relations: {exc}") from None


def _sqrt0(variance: float) -> float:
    """√variance, with the tiny negative round-off of an exact relation read as 0."""
    return float(np.sqrt(max(variance, 0.0)))


def _moments(rise_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = rise_C.mean(axis=0)
    centred = rise_C - mean
    return mean, centred.T @ centred / rise_C.shape[0]


def fit_relations(
    rise_C: np.ndarray, sensors: Sequence[str], run_index: np.ndarray | None = None
) -> SensorRelations:
    """Fit the relations on training rises (n × p, °C); ``run_index`` labels each row's run.

    With two or more runs, each sensor's held-out σ is the RMS of its
    leave-one-run-out residuals (each run predicted by the moments of the other
    runs); with one run it is the in-sample σ.
    """
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
    mean, cov = _moments(X)
    if labels.size < 2:
        full = SensorRelations(names, mean, cov, dict.fromkeys(names, 0.0), X.shape[0], 1)
        held = {s: full.relation(s, names)[2] for s in names}
        return SensorRelations(names, mean, cov, held, X.shape[0], 1)
    squared = np.zeros(len(names))
    for label in labels:
        test = runs == label
        train = ~test
        if train.sum() < len(names):
            raise ValueError(f"run {label}: too few rows in the other runs to fit a relation")
        fold = SensorRelations(names, *_moments(X[train]), dict.fromkeys(names, 0.0), 0, 0)
        for k, sensor in enumerate(names):
            intercept, coefficients, _ = fold.relation(sensor, names)
            b = np.array([coefficients[s] for s in names if s != sensor])
            others = np.delete(X[test], k, axis=1)
            residual = X[test, k] - intercept - others @ b
            squared[k] += float(residual @ residual)
    held = {s: float(np.sqrt(squared[k] / X.shape[0])) for k, s in enumerate(names)}
    return SensorRelations(names, mean, cov, held, X.shape[0], int(labels.size))
