"""A model store for a multi-axis machine: one small model per error column, for tests.

The synthetic runs of :mod:`tests.synthetic` with a different known error per axis
(each a linear combination of two sensors' rises), fitted by MLR on the sensors given
(default: all seven) and stored under a target name of its own, as ``fit --target``
stores them.
"""

from __future__ import annotations

from pathlib import Path

from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.registry import make_model
from models.store import ModelStore
from tests.synthetic import stored_document, write_runs_csv

#: Per target: its sensors' weights, µm per °C of rise.
AXIS_ERRORS: dict[str, dict[str, float]] = {
    "z_um": {"T1": 4.0, "T6": -2.0},
    "x_um": {"T2": 1.5, "T7": -1.0},
    "y_um": {"T3": -1.0, "T5": 0.5},
}


def model_id_of(target: str) -> str:
    return f"mlr-{target}-all"


def axes_store(
    folder: Path,
    targets: dict[str, dict[str, float]] | None = None,
    sensors: dict[str, list[str]] | None = None,
) -> Path:
    """``folder/models``: one MLR model per target (id ``mlr-<target>-all``), on the
    sensors ``sensors[target]`` names (default: T1…T7)."""
    store = ModelStore(folder / "models")
    for target, weights in (targets or AXIS_ERRORS).items():
        runs = write_runs_csv(folder / f"runs-{target}.csv", error_weights=weights)
        if sensors and target in sensors:
            keep_columns(runs, ["run", "time_s", "speed_rpm", *sensors[target], "error_um"])
        prepared = prepare(load_runs(runs))
        model = make_model("mlr").fit(prepared.inputs, prepared.error_um)
        store.save(stored_document(prepared, model, model_id_of(target), target=target))
    return folder / "models"


def keep_columns(path: Path, columns: list[str]) -> None:
    """Rewrite the CSV at ``path`` with ``columns`` only (a recording of fewer sensors)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    header = lines[0].split(",")
    keep = [header.index(c) for c in columns]
    rows = [",".join(line.split(",")[i] for i in keep) for line in lines]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
