"""How low can leave-one-run-out go with the analysis' kinds of terms, and what does honesty cost?

``analyze`` may only add an effect that held-out data and a significance test
both support, with every parameter chosen on training runs. This script builds
a library of every single term the effect families could offer (each sensor's
rise as is and lagged with τ from 5 min to 8 h, n and n² as is and lagged up to
8 h, hours since the recording started) and asks three questions per channel:

- ``optimistic_bound``: the best subset of up to ``--max-terms`` terms, found by
  forward selection then one-for-one swaps, *judged on the held-out runs
  themselves*. Choosing on the data it is scored on makes this figure
  optimistic: it says the terms exist, not that anyone could find them.
- ``honest_selection``: the same search, but for each held-out run it is made
  on the other runs only (an inner leave-one-run-out), then the chosen terms are
  fitted on those runs and scored on the held-out one: what an unrestricted,
  honest term search achieves.
- ``honest_ridge``: every sensor plus its first-order lags at one τ, fitted with
  a ridge penalty; τ and the penalty chosen by the same inner leave-one-run-out.
  Shrinkage instead of selection, for comparison.

Prints one JSON document.

    .venv/bin/python benchmarks/heldout_bound.py [--targets ch1_um,ch3_um,ch5_um] [--max-terms 10]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from models.data.dataset import load_runs  # noqa: E402
from models.data.features import prepare  # noqa: E402
from models.data.lag_terms import first_order_lag, hours_since_start  # noqa: E402

SENSOR_TAUS_S = (0.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
SPEED_TAUS_S = (0.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
RIDGE_PENALTIES = (0.0, 1e-4, 1e-3, 1e-2, 1e-1)


def term_library(path: Path, target: str) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """Names and columns of every candidate term, the target rise (µm) and the run of each row."""
    prepared = prepare(load_runs(path, target=target))
    data = prepared.data
    recording = prepared.plan.recording
    sensor_rises = prepared.inputs.rise_C
    speed_krpm = data.speed_rpm / 1000.0
    speed_rises = prepared.plan.rises(np.column_stack([speed_krpm, speed_krpm**2]))
    names: list[str] = []
    columns: list[np.ndarray] = []
    for tau in SENSOR_TAUS_S:
        block = (
            sensor_rises if tau == 0 else first_order_lag(sensor_rises, data.time_s, recording, tau)
        )
        names += [f"{s} (τ {tau:g} s)" for s in prepared.inputs.sensors]
        columns.append(block)
    for tau in SPEED_TAUS_S:
        block = (
            speed_rises if tau == 0 else first_order_lag(speed_rises, data.time_s, recording, tau)
        )
        names += [f"n (τ {tau:g} s)", f"n² (τ {tau:g} s)"]
        columns.append(block)
    names.append("hours since the recording started")
    columns.append(hours_since_start(data.time_s, recording)[:, None])
    return names, np.column_stack(columns), prepared.error_um, data.run_index


def sensor_columns(names: list[str], tau: float) -> list[int]:
    """Library indices of every sensor's term at ``tau`` (0: the rise as it is)."""
    return [
        j
        for j, name in enumerate(names)
        if name.startswith("T") and name.endswith(f"(τ {tau:g} s)")
    ]


class HeldOut:
    """Leave-one-run-out fits of any subset of columns, from per-run Gram matrices.

    ``runs`` restricts the folds to some runs (an inner validation inside one
    outer training set); every fold's fit uses the other runs of that subset.
    """

    def __init__(self, columns: np.ndarray, y: np.ndarray, run: np.ndarray) -> None:
        z = np.column_stack([np.ones(y.size), columns])
        labels = np.unique(run)
        self.gram = np.stack([z[run == r].T @ z[run == r] for r in labels])
        self.cross = np.stack([z[run == r].T @ y[run == r] for r in labels])
        self.yy = np.array([y[run == r] @ y[run == r] for r in labels])
        self.count = np.array([np.count_nonzero(run == r) for r in labels])

    @property
    def n_runs(self) -> int:
        return self.yy.size

    def fit(self, idx: list[int], runs: list[int], ridge: float = 0.0) -> np.ndarray:
        """Coefficients of columns ``idx`` (0 = intercept) fitted on ``runs``.

        ``ridge`` penalises each term by ridge × n × its variance (a ridge on
        standardised columns); the intercept is never penalised.
        """
        block = np.ix_(idx, idx)
        g = self.gram[runs].sum(0)[block]
        c = self.cross[runs].sum(0)[idx]
        if ridge > 0:
            n = self.count[runs].sum()
            mean = g[0] / n
            variance = np.diag(g) / n - mean**2
            variance[0] = 0.0
            g = g + ridge * n * np.diag(variance)
        return np.linalg.lstsq(g, c, rcond=None)[0]

    def sse(self, idx: list[int], run: int, beta: np.ndarray) -> float:
        block = np.ix_(idx, idx)
        return float(
            self.yy[run] - 2 * beta @ self.cross[run][idx] + beta @ self.gram[run][block] @ beta
        )

    def rmse_um(
        self, chosen: list[int], runs: list[int] | None = None, ridge: float = 0.0
    ) -> float:
        """Pooled leave-one-run-out RMSE of the intercept plus ``chosen`` columns over ``runs``."""
        runs = list(range(self.n_runs)) if runs is None else runs
        idx = [0, *(c + 1 for c in chosen)]
        sse = 0.0
        for k in runs:
            beta = self.fit(idx, [r for r in runs if r != k], ridge)
            sse += self.sse(idx, k, beta)
        return float(np.sqrt(max(sse, 0.0) / self.count[runs].sum()))


def best_subset(
    n_terms: int, score: Callable[[list[int]], float], max_terms: int
) -> tuple[float, list[int]]:
    """Forward selection (stops when a term gains < 1 %), then one-for-one swaps while any helps."""
    chosen: list[int] = []
    best = float("inf")
    for _ in range(max_terms):
        rmse, pick = min((score([*chosen, j]), j) for j in range(n_terms) if j not in chosen)
        if rmse > 0.99 * best:
            break
        chosen, best = [*chosen, pick], rmse
    improved = True
    while improved:
        improved = False
        for position in range(len(chosen)):
            for j in range(n_terms):
                if j in chosen:
                    continue
                trial = [*chosen[:position], j, *chosen[position + 1 :]]
                rmse = score(trial)
                if rmse < best - 1e-4:
                    chosen, best, improved = trial, rmse, True
    return best, chosen


def honest_selection(
    names: list[str], held: HeldOut, max_terms: int
) -> tuple[float, list[list[str]]]:
    """Held-out RMSE when each fold's terms are chosen on that fold's training runs only."""
    sse, picks = 0.0, []
    for k in range(held.n_runs):
        train = [r for r in range(held.n_runs) if r != k]
        _, chosen = best_subset(
            len(names), lambda c, train=train: held.rmse_um(c, train), max_terms
        )
        idx = [0, *(c + 1 for c in chosen)]
        sse += held.sse(idx, k, held.fit(idx, train))
        picks.append([names[c] for c in chosen])
    return float(np.sqrt(sse / held.count.sum())), picks


def honest_ridge(names: list[str], held: HeldOut) -> tuple[float, list[dict[str, float]]]:
    """Held-out RMSE of all sensors + their lags at one τ under a ridge penalty, τ and penalty
    chosen by inner leave-one-run-out on each fold's training runs."""
    options = [
        (tau, ridge, sensor_columns(names, 0.0) + sensor_columns(names, tau))
        for tau in SENSOR_TAUS_S[1:]
        for ridge in RIDGE_PENALTIES
    ]
    sse, picks = 0.0, []
    for k in range(held.n_runs):
        train = [r for r in range(held.n_runs) if r != k]
        _, tau, ridge, chosen = min(
            (held.rmse_um(cols, train, ridge), tau, ridge, cols) for tau, ridge, cols in options
        )
        idx = [0, *(c + 1 for c in chosen)]
        sse += held.sse(idx, k, held.fit(idx, train, ridge))
        picks.append({"tau_s": tau, "ridge": ridge})
    return float(np.sqrt(sse / held.count.sum())), picks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data" / "fl_thermal.csv")
    parser.add_argument("--targets", default="ch1_um,ch3_um,ch5_um")
    parser.add_argument("--max-terms", type=int, default=10)
    args = parser.parse_args()
    results = {}
    for target in args.targets.split(","):
        names, columns, y, run = term_library(args.data, target)
        held = HeldOut(columns, y, run)
        bound, chosen = best_subset(len(names), held.rmse_um, args.max_terms)
        selection, selection_terms = honest_selection(names, held, args.max_terms)
        ridge, ridge_choices = honest_ridge(names, held)
        results[target] = {
            "plain_linear_all_sensors_rmse_um": round(held.rmse_um(sensor_columns(names, 0.0)), 2),
            "optimistic_bound_rmse_um": round(bound, 2),
            "optimistic_bound_terms": [names[j] for j in chosen],
            "honest_selection_rmse_um": round(selection, 2),
            "honest_selection_terms_per_fold": selection_terms,
            "honest_ridge_rmse_um": round(ridge, 2),
            "honest_ridge_choice_per_fold": ridge_choices,
        }
    print(
        json.dumps(
            {
                "data": args.data.name,
                "validation": "leave-one-run-out",
                "library_terms": len(names),
                "max_terms": args.max_terms,
                "results": results,
            },
            indent=2,
            ensure_ascii=False,
        )
    )


if __name__ == "__main__":
    main()
