"""How far apart can two leave-one-run-out figures be and still say nothing?

A held-out RMSE over six cycles is an average over six cycles, and the cycles
differ: on ``fl_thermal.csv`` ch1 lag-ridge leaves 0.90 µm in one and 2.23 µm in
another. This script resamples the held-out runs of ``fit --json`` results
(scipy's bootstrap, the runs drawn with replacement, each keeping its squared
error and row count) and prints:

- for each file, the pooled RMSE and its 90 % interval over the runs;
- for each file after the first, the paired difference from the first (the same
  runs drawn for both, so what the runs share cancels) with its 90 % interval
  and the share of resamples in which it is the lower.

The interval says how much the figure would move on another six cycles like
these; it does not make any figure more or less honest. Nothing here is chosen.

    .venv/bin/python -m gateway fit data/fl_thermal.csv --method lag-ridge \\
        --target ch1_um --json a.json
    .venv/bin/python benchmarks/heldout_spread.py a.json [b.json ...] [--scheme all]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import bootstrap

RESAMPLES = 20_000
LEVEL = 0.90


def per_run(path: Path, scheme: str) -> dict[str, tuple[float, int]]:
    """Run → (squared-error sum µm², rows) of one ``fit --json`` validation."""
    folds = json.loads(path.read_text(encoding="utf-8"))["validations"][scheme]["per_fold"]
    return {
        run: (f["rmse_um"] ** 2 * f["n_samples"], int(f["n_samples"])) for run, f in folds.items()
    }


def pooled_rmse(sse: np.ndarray, rows: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.sqrt(np.sum(sse, axis=axis) / np.sum(rows, axis=axis))


def interval(statistic, *samples: np.ndarray) -> tuple[float, float]:
    result = bootstrap(
        samples,
        statistic,
        paired=True,
        vectorized=True,
        n_resamples=RESAMPLES,
        confidence_level=LEVEL,
        method="percentile",
        random_state=np.random.default_rng(0),
    )
    low, high = result.confidence_interval
    return round(float(low), 3), round(float(high), 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", type=Path, help="fit --json files")
    parser.add_argument("--scheme", default="all", help="the validation scheme (default all)")
    args = parser.parse_args()
    runs = [per_run(p, args.scheme) for p in args.results]
    names = sorted(runs[0])
    for other, path in zip(runs[1:], args.results[1:], strict=True):
        if sorted(other) != names:
            raise SystemExit(f"{path}: held-out runs {sorted(other)} differ from {names}")
    sse = np.array([[r[n][0] for n in names] for r in runs])
    rows = np.array([runs[0][n][1] for n in names])
    if any([r[n][1] for n in names] != rows.tolist() for r in runs[1:]):
        raise SystemExit("the files' held-out runs have different row counts")
    report: dict[str, dict] = {}
    for k, path in enumerate(args.results):
        entry: dict = {
            "pooled_rmse_um": round(float(pooled_rmse(sse[k], rows)), 3),
            f"interval_{LEVEL:.0%}_um": interval(pooled_rmse, sse[k], rows),
        }
        if k:

            def difference(a, b, n, axis=-1):
                return pooled_rmse(b, n, axis) - pooled_rmse(a, n, axis)

            entry[f"minus_first_um_{LEVEL:.0%}"] = interval(difference, sse[0], sse[k], rows)
            draws = np.random.default_rng(1).integers(0, len(names), (RESAMPLES, len(names)))
            lower = pooled_rmse(sse[k][draws], rows[draws]) < pooled_rmse(
                sse[0][draws], rows[draws]
            )
            entry["lower_than_first_share"] = round(float(lower.mean()), 3)
        report[str(path)] = entry
    print(json.dumps(report, indent=1, ensure_ascii=False))


if __name__ == "__main__":
    main()
