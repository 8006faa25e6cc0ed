"""fl_thermal forward: fit on cycles c1-c4, score c5-c6 as a new recording, as a plant does.

A plant fits on last month's runs and runs the model on next month's. This writes the
first four cycles of ``data/fl_thermal.csv`` (30 h) and the last two (16 h) as files of
their own, fits each method on the first with its defaults and scores it on the second
the way ``score`` does (a new recording: its own cold reference, every lag started at
its first sample). With ``--loro`` it also gives each method's leave-one-cycle-out
figure on the whole file and the forward figure ``fit`` reports on it
(:mod:`models.fit.forward`). Nothing here chooses anything: the methods are fixed in
the code before they are scored.

    .venv/bin/python benchmarks/forward_split.py [--loro] [--methods lag-ridge,ridge,mlr]
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
from pathlib import Path

import numpy as np

from models.data.dataset import load_runs
from models.data.features import prepare
from models.estimators.registry import make_model
from models.fit.crossval import cross_validate
from models.fit.forward import forward_validate

DATA = Path(__file__).resolve().parent.parent / "data" / "fl_thermal.csv"
CHANNELS = ("ch1_um", "ch3_um", "ch5_um")


def split_files(folder: Path) -> tuple[Path, Path]:
    """c1-c4 and c5-c6 of fl_thermal as two files."""
    early, later = folder / "fl_c1_c4.csv", folder / "fl_c5_c6.csv"
    with DATA.open(newline="") as source:
        rows = list(csv.reader(source))
    for path, prefixes in ((early, ("c1", "c2", "c3", "c4")), (later, ("c5", "c6"))):
        with path.open("w", newline="") as out:
            writer = csv.writer(out)
            writer.writerow(rows[0])
            writer.writerows(r for r in rows[1:] if r[0].startswith(prefixes))
    return early, later


def rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e))))


def measure(method: str, channel: str, early: Path, later: Path, loro: bool) -> dict:
    train = prepare(load_runs(early, target=channel))
    test = prepare(load_runs(later, target=channel))
    model = make_model(method).fit(train.inputs, train.error_um)
    figures = {"forward_split_rmse_um": rmse(test.error_um - model.predict(test.inputs))}
    if loro:
        data = load_runs(DATA, target=channel)
        whole = prepare(data)

        def factory():
            return make_model(method)

        figures["loro_rmse_um"] = cross_validate(factory, whole).pooled.rmse_um
        forward = forward_validate(factory, whole, data)
        figures["fit_forward_rmse_um"] = None if forward is None else forward.pooled.rmse_um
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default="lag-ridge,ridge,mlr")
    parser.add_argument("--loro", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        early, later = split_files(Path(folder))
        results = {
            method: {ch: measure(method, ch, early, later, args.loro) for ch in CHANNELS}
            for method in args.methods.split(",")
        }
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
