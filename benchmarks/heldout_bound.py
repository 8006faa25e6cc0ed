"""How low can leave-one-run-out go with the analysis' kinds of terms? An optimistic bound.

``analyze`` may only add an effect that held-out data and a significance test
both support, with every parameter chosen on training runs. This script drops
those guards to see what the *data* allow at best: it builds a library of every
term the effect families could offer, one column at a time (each sensor's rise
as is and lagged with τ from 5 min to 8 h, n and n² as is and lagged up to 8 h,
hours since the recording started) and selects greedily, term after term, the
one that lowers the pooled leave-one-run-out RMSE most, judged on the held-out
runs themselves. Choosing on the held-out runs makes the figure optimistic: no
honest procedure can expect to beat it with these terms.

Prints one JSON document: per channel the plain linear model on all sensors,
the best figure reached and the terms that reached it.

    .venv/bin/python benchmarks/heldout_bound.py [--targets ch1_um,ch3_um,ch5_um] [--max-terms 10]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from models.dataset import load_runs  # noqa: E402
from models.effect_terms import first_order_lag, hours_since_start  # noqa: E402
from models.features import prepare  # noqa: E402
from models.references import rises  # noqa: E402

SENSOR_TAUS_S = (0.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
SPEED_TAUS_S = (0.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)


def term_library(path: Path, target: str) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """Names and columns of every candidate term, the target rise (µm) and the run of each row."""
    prepared = prepare(load_runs(path, target=target))
    data = prepared.data
    recording = prepared.plan.recording
    sensor_rises = prepared.inputs.rise_C
    speed_krpm = data.speed_rpm / 1000.0
    speed_rises = rises(np.column_stack([speed_krpm, speed_krpm**2]), recording)
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


class HeldOut:
    """Pooled leave-one-run-out RMSE of any subset of columns, from per-run Gram matrices."""

    def __init__(self, columns: np.ndarray, y: np.ndarray, run: np.ndarray) -> None:
        z = np.column_stack([np.ones(y.size), columns])
        runs = np.unique(run)
        self.gram = np.stack([z[run == r].T @ z[run == r] for r in runs])
        self.cross = np.stack([z[run == r].T @ y[run == r] for r in runs])
        self.yy = np.array([y[run == r] @ y[run == r] for r in runs])
        self.n = y.size

    def rmse_um(self, chosen: list[int]) -> float:
        idx = [0, *(c + 1 for c in chosen)]
        block = np.ix_(idx, idx)
        sse = 0.0
        for k in range(self.yy.size):
            g = (self.gram.sum(0) - self.gram[k])[block]
            c = (self.cross.sum(0) - self.cross[k])[idx]
            beta = np.linalg.lstsq(g, c, rcond=None)[0]
            sse += self.yy[k] - 2 * beta @ self.cross[k][idx] + beta @ self.gram[k][block] @ beta
        return float(np.sqrt(max(sse, 0.0) / self.n))


def greedy_bound(names: list[str], held: HeldOut, max_terms: int) -> tuple[float, list[str]]:
    chosen: list[int] = []
    best = (float("inf"), chosen)
    for _ in range(max_terms):
        rmse, pick = min(
            (held.rmse_um([*chosen, j]), j) for j in range(len(names)) if j not in chosen
        )
        chosen = [*chosen, pick]
        if rmse < best[0]:
            best = (rmse, chosen)
    return best[0], [names[j] for j in best[1]]


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
        n_sensors = sum(1 for name in names if name.endswith("(τ 0 s)") and name.startswith("T"))
        bound, terms = greedy_bound(names, held, args.max_terms)
        results[target] = {
            "plain_linear_all_sensors_rmse_um": round(held.rmse_um(list(range(n_sensors))), 2),
            "optimistic_bound_rmse_um": round(bound, 2),
            "terms": terms,
        }
    print(
        json.dumps(
            {
                "data": args.data.name,
                "validation": "leave-one-run-out, terms chosen on the held-out runs (optimistic)",
                "library_terms": len(names),
                "results": results,
            },
            indent=2,
            ensure_ascii=False,
        )
    )


if __name__ == "__main__":
    main()
