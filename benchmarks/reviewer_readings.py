"""Readings of two outside procedures for ``data/fl_thermal.csv``, each fully nested.

An outside review reported leave-one-cycle-out figures for two procedures:

- *ridge*: one penalty over every sensor's rise, its first-order lags at the ten
  τ of ``DEFAULT_TAUS_S`` (5 min … 24 h) and the speed with the same lags;
- *lasso*: the sensors and their 30 min lags, the penalty chosen on inner folds.

Their descriptions leave details open, so every plausible reading is run:
terms standardised or in their own units (°C; n in 1000 r/min or in r/min); the
speed as n only or as n, n^1.5, n², n^2.5; the penalty grid (``lag-ridge``'s or
a wider one; for the lasso ``lag-ridge``'s σ-relative grid or scikit-learn
``LassoCV``'s 100 values from the largest useful one); the inner scheme
(leave-one-cycle-out or five contiguous row blocks of the training cycles,
scikit-learn's unshuffled ``KFold(5)``; leave-one-row-out, ``RidgeCV``'s
default) and its score (pooled squared error, mean per-fold RMSE, mean
per-fold MSE). In every reading the penalty is chosen inside each outer
training set; the figure is the pooled RMSE over the six held-out cycles.
Picking one reading by these figures would make it optimistic: they are
printed side by side, never chosen among.

Prints one JSON document (reading → RMSE µm per target).

    .venv/bin/python benchmarks/reviewer_readings.py [--targets ch1_um,ch3_um,ch5_um]
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from models.data.dataset import load_runs  # noqa: E402
from models.data.features import prepare  # noqa: E402
from models.estimators.lag_ridge import lag_terms  # noqa: E402
from models.estimators.lag_structures import (  # noqa: E402
    DEFAULT_SPEED_POWERS,
    DEFAULT_TAUS_S,
    LASSO_PENALTIES,
    PENALTIES,
    GroupGrams,
    ridge_path,
)

FL_THERMAL = ROOT / "data" / "fl_thermal.csv"
#: A wider ridge grid than ``lag-ridge``'s (relative to the row count, as there).
WIDE_PENALTIES = tuple(float(a) for a in np.logspace(-9, 4, 53))
SCORINGS = ("pooled-sse", "mean-rmse", "mean-mse")
#: A path: [intercept, coefficients] per grid point, fitted on the given rows.
Path_ = Callable[[np.ndarray, np.ndarray], list[np.ndarray]]


def blocks(n: int, k: int = 5) -> np.ndarray:
    """Labels of ``k`` contiguous row blocks (scikit-learn's unshuffled ``KFold``)."""
    return np.minimum(np.arange(n) * k // max(n, 1), k - 1)


def nested_rmse(
    terms: np.ndarray,
    y: np.ndarray,
    runs: np.ndarray,
    fit: Path_,
    inner: str,
    grids: dict[str, slice] | None = None,
) -> dict[tuple[str, str], float]:
    """Outer leave-one-run-out RMSE per (grid, inner score): the grid point chosen within
    each part ``grids`` of the path on the training runs' inner folds (``inner``:
    ``cycles`` or ``blocks5``)."""
    parts = {"": slice(None)} if grids is None else grids
    predicted = {(g, s): np.empty_like(y) for g in parts for s in SCORINGS}
    for held in np.unique(runs):
        train = runs != held
        z, t = terms[train], y[train]
        labels = runs[train] if inner == "cycles" else blocks(t.size)
        sse, counts = [], []
        for fold in np.unique(labels):
            out = labels == fold
            path = fit(z[~out], t[~out])
            sse.append([float(np.sum((t[out] - b[0] - z[out] @ b[1:]) ** 2)) for b in path])
            counts.append(int(out.sum()))
        sse_a, n_a = np.array(sse), np.array(counts)[:, None]
        scores = {
            "pooled-sse": sse_a.sum(0),
            "mean-rmse": np.sqrt(sse_a / n_a).mean(0),
            "mean-mse": (sse_a / n_a).mean(0),
        }
        full = fit(z, t)
        for grid, part in parts.items():
            offset = range(len(full))[part].start
            for name, score in scores.items():
                b = full[offset + int(np.argmin(score[part]))]
                predicted[grid, name][~train] = b[0] + terms[~train] @ b[1:]
    return {k: float(np.sqrt(np.mean((y - p) ** 2))) for k, p in predicted.items()}


def ridge(penalties: Sequence[float], standardise: bool) -> Path_:
    def fit(z: np.ndarray, t: np.ndarray) -> list[np.ndarray]:
        gram = GroupGrams(z, t, np.zeros(t.size, dtype=int))
        g, c = gram.total([0])
        return ridge_path(g, c, np.zeros(z.shape[1], dtype=int), 1.0, penalties, standardise)

    return fit


def lasso(standardise: bool, grid: str) -> Path_:
    """Lasso path (scikit-learn) on centred terms; ``grid``: ``sigma`` (``lag-ridge``'s
    grid × the target's σ) or ``lassocv`` (100 values from the largest useful, eps 1e-3)."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.linear_model import lasso_path

    def fit(z: np.ndarray, t: np.ndarray) -> list[np.ndarray]:
        mean, y_mean = z.mean(0), t.mean()
        scale = (z - mean).std(0) if standardise else np.ones(z.shape[1])
        scale[scale < 1e-12] = 1.0
        x, yc = (z - mean) / scale, t - y_mean
        if grid == "sigma":
            alphas = float(np.std(yc)) * np.asarray(LASSO_PENALTIES)
        else:
            largest = float(np.max(np.abs(x.T @ yc))) / t.size
            alphas = np.logspace(np.log10(largest), np.log10(largest * 1e-3), 100)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            _, coefs, _ = lasso_path(x, yc, alphas=alphas, max_iter=5000, precompute=True)
        return [np.r_[y_mean - mean @ (w / scale), w / scale] for w in coefs.T]

    return fit


def ridge_row_loo(terms: np.ndarray, y: np.ndarray, runs: np.ndarray, standardise: bool) -> float:
    """``RidgeCV``'s default: the penalty by leave-one-*row*-out (efficient GCV)."""
    from sklearn.linear_model import RidgeCV

    predicted = np.empty_like(y)
    for held in np.unique(runs):
        train = runs != held
        mean = terms[train].mean(0)
        scale = terms[train].std(0) if standardise else np.ones(terms.shape[1])
        scale[scale < 1e-12] = 1.0
        x = (terms - mean) / scale
        model = RidgeCV(alphas=np.logspace(-6, 6, 25)).fit(x[train], y[train])
        predicted[~train] = model.predict(x[~train])
    return float(np.sqrt(np.mean((y - predicted) ** 2)))


def speed_in_rpm(terms: np.ndarray, n_sensors: int, powers: Sequence[float]) -> np.ndarray:
    """The same terms with every speed column in r/min^p instead of (1000 r/min)^p."""
    out = terms.copy()
    width = n_sensors + len(powers)
    for block in range(terms.shape[1] // width):
        for j, p in enumerate(powers):
            out[:, block * width + n_sensors + j] *= 1000.0**p
    return out


def readings(target: str) -> dict[str, float]:
    prepared = prepare(load_runs(FL_THERMAL, target=target))
    inputs, y = prepared.inputs, prepared.error_um
    runs = np.asarray(inputs.run_index)
    sensors = inputs.sensors
    result: dict[str, float] = {}
    for powers, speed in (((1.0,), "n"), (DEFAULT_SPEED_POWERS, "n..n^2.5")):
        base = lag_terms(inputs, sensors, DEFAULT_TAUS_S, powers)
        units = [("standardised", base, True), ("raw °C, n krpm", base, False)]
        if powers == (1.0,):  # n^2.5 in r/min is ~1e9: not a reading anyone fits
            units.append(("raw °C, n rpm", speed_in_rpm(base, len(sensors), powers), False))
        grids = {
            "lag-ridge grid": slice(0, len(PENALTIES)),
            "wide grid": slice(len(PENALTIES), None),
        }
        for unit, terms, standardise in units:
            fit = ridge(PENALTIES + WIDE_PENALTIES, standardise)
            for inner in ("cycles", "blocks5"):
                scores = nested_rmse(terms, y, runs, fit, inner, grids)
                for (grid_name, scoring), rmse in scores.items():
                    key = f"ridge | {speed} | {unit} | {grid_name} | {inner} {scoring}"
                    result[key] = rmse
            result[f"ridge | {speed} | {unit} | RidgeCV alphas | row LOO (GCV)"] = ridge_row_loo(
                terms, y, runs, standardise
            )
    terms = lag_terms(inputs, sensors, (1800.0,), ())
    for unit, standardise in (("standardised", True), ("raw °C", False)):
        for grid in ("sigma", "lassocv"):
            for inner in ("cycles", "blocks5"):
                scores = nested_rmse(terms, y, runs, lasso(standardise, grid), inner)
                for (_, scoring), rmse in scores.items():
                    result[f"lasso 30min | {unit} | {grid} grid | {inner} {scoring}"] = rmse
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", default="ch1_um,ch3_um,ch5_um")
    args = parser.parse_args()
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        table = {t: readings(t) for t in args.targets.split(",")}
    print(json.dumps({"rmse_um": table}, indent=1, ensure_ascii=False))


if __name__ == "__main__":
    main()
