"""Small synthetic measured runs with known structure, for tests.

Each run is a speed programme; every sensor follows the speed-driven heat input
through a first-order lag of its own time constant and gain; the error is a known
linear combination of two sensors' rises plus noise. Not the product's simulator:
just enough physics for the maths to have something true to find.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

SENSOR_TAUS_S = (600.0, 700.0, 800.0, 900.0, 3000.0, 3300.0, 3600.0)
SENSOR_GAINS = (3.0, 2.6, 2.2, 1.8, 1.5, 1.2, 1.0)
ERROR_WEIGHTS = {"T1": 4.0, "T6": -2.0}


def first_order(drive: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    out = np.zeros_like(drive)
    a = np.exp(-dt_s / tau_s)
    for k in range(1, drive.size):
        out[k] = a * out[k - 1] + (1 - a) * drive[k - 1]
    return out


def speed_programme(kind: int, n: int) -> np.ndarray:
    third = n // 3
    levels = [
        [2000, 6000, 0],
        [6000, 2000, 4000],
        [4000, 4000, 4000],
        [0, 3000, 6000],
        [5000, 0, 5000],
    ][kind % 5]
    speed = np.repeat(np.asarray(levels, dtype=float), third)
    return np.pad(speed, (0, n - speed.size), mode="edge")


def make_runs(
    n_runs: int = 4,
    n: int = 300,
    dt_s: float = 60.0,
    noise_um: float = 0.3,
    seed: int = 0,
    error_weights: dict[str, float] | None = None,
):
    """Rows (run, time_s, speed_rpm, T1..T7, error_um) as a list of lists.

    ``error_weights`` (µm/°C per sensor rise) defaults to ``ERROR_WEIGHTS``.
    """
    weights = ERROR_WEIGHTS if error_weights is None else error_weights
    rng = np.random.default_rng(seed)
    rows = []
    for r in range(n_runs):
        speed = speed_programme(r, n)
        drive = (speed / 6000.0) ** 1.5
        temps = np.column_stack(
            [
                20.0 + g * 10 * first_order(drive, tau, dt_s)
                for tau, g in zip(SENSOR_TAUS_S, SENSOR_GAINS, strict=True)
            ]
        )
        temps += rng.normal(0, 0.02, temps.shape)
        error = sum(
            w * (temps[:, int(name[1:]) - 1] - temps[0, int(name[1:]) - 1])
            for name, w in weights.items()
        )
        error = error + rng.normal(0, noise_um, n)
        for k in range(n):
            rows.append([f"R{r + 1}", k * dt_s, speed[k], *temps[k], error[k]])
    return rows


def write_runs_csv(path: Path, **kwargs) -> Path:
    header = [
        "run",
        "time_s",
        "speed_rpm",
        *[f"T{i + 1}" for i in range(len(SENSOR_TAUS_S))],
        "error_um",
    ]
    lines = [",".join(header)]
    for row in make_runs(**kwargs):
        lines.append(",".join([row[0], *(f"{v:.6g}" for v in row[1:])]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def stored_document(prepared, model, model_id: str, **changes: Any) -> dict[str, Any]:
    """The store document of ``model`` fitted on every run of ``prepared`` (regime "all",
    validated leave-one-run-out); ``changes`` replace arguments of ``build_document``."""
    from models.store import build_document

    arguments: dict[str, Any] = {
        "model_id": model_id,
        "inputs": prepared.inputs,
        "error_um": prepared.error_um,
        "target": "error_um",
        "source_file": prepared.data.source,
        "runs": list(prepared.data.run_ids),
        "reference": prepared.plan.describe(),
        "regime": "all",
        "validation": {"scheme": "leave-one-run-out"},
        "software_version": "test",
    }
    return build_document(model, **(arguments | changes))


#: Error weights of the three axes of :func:`write_axes_csv` (µm/°C per sensor rise).
AXIS_WEIGHTS = {
    "x_um": {"T2": 1.5, "T5": -0.8},
    "y_um": {"T3": -2.0, "T7": 1.0},
    "z_um": ERROR_WEIGHTS,
}


def write_axes_csv(path: Path, empty_rows: dict[str, int] | None = None, **kwargs) -> Path:
    """Runs with three error columns (x_um, y_um, z_um), one per axis, from the same
    temperatures; ``empty_rows``: an error column with one empty cell at that data row."""
    names = list(AXIS_WEIGHTS)
    tables = [make_runs(error_weights=AXIS_WEIGHTS[name], **kwargs) for name in names]
    header = ["run", "time_s", "speed_rpm", *[f"T{i + 1}" for i in range(len(SENSOR_TAUS_S))]]
    lines = [",".join([*header, *names])]
    for k, row in enumerate(tables[0]):
        cells = [f"{table[k][-1]:.6g}" for table in tables]
        for column, at in (empty_rows or {}).items():
            if at == k:
                cells[names.index(column)] = ""
        lines.append(",".join([row[0], *(f"{v:.6g}" for v in row[1:-1]), *cells]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
