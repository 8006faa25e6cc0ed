"""Validation on data the fit did not see.

- Leave-one-run-out: for each run, fit on every other run and predict it.
  Runs are the natural unit (an experiment, a shift, a heating–cooling cycle):
  neighbouring samples of one run are strongly correlated, so any split inside a
  run would flatter the model.
- One run only: the run is cut into ``BLOCKS`` (5) contiguous blocks and each
  block is predicted by a model fitted on the other four (a blocked split).
- Cross-evaluation (paper 002 §5): one model per run, evaluated on every run,
  giving the σ matrix that regime ranking works on.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from models.base import ThermalModel
from models.data.features import Prepared
from models.fit.metrics import Accuracy, accuracy
from models.fit.ranking import SigmaRow

BLOCKS = 5
ModelFactory = Callable[[], ThermalModel]


@dataclass(frozen=True)
class Validation:
    """Held-out predictions and their accuracy, per fold and pooled."""

    scheme: str
    folds: tuple[str, ...]
    per_fold: dict[str, Accuracy]
    pooled: Accuracy
    predicted_um: np.ndarray  # (n,) held-out prediction of every row

    def as_dict(self) -> dict[str, object]:
        return {
            "scheme": self.scheme,
            "pooled": self.pooled.as_dict(),
            "per_fold": {name: acc.as_dict() for name, acc in self.per_fold.items()},
        }


def fold_labels(prepared: Prepared) -> tuple[str, np.ndarray]:
    """(scheme, label of each row): its run, or its block when there is one run."""
    runs = prepared.data.run
    if len(prepared.data.run_ids) >= 2:
        return "leave-one-run-out", runs  # the run ids themselves: no string copy per row
    n = prepared.data.n_samples
    if n < BLOCKS * 2:
        raise ValueError(
            f"{prepared.data.source}: one run of {n} samples is too short for a blocked "
            f"split into {BLOCKS} blocks; at least {BLOCKS * 2} samples, or two runs, "
            "were expected"
        )
    block = np.minimum(np.arange(n) * BLOCKS // n, BLOCKS - 1)
    labels = np.array([f"{runs[0]}#block{b + 1}" for b in block], dtype=object)
    return f"leave-one-block-out ({BLOCKS} contiguous blocks of the single run)", labels


#: From this many folds on, the folds are fitted in parallel processes (one per core).
PARALLEL_FROM_FOLDS = 12


def cross_validate(factory: ModelFactory, prepared: Prepared, progress: bool = False) -> Validation:
    scheme, labels = fold_labels(prepared)
    folds = tuple(dict.fromkeys(labels))
    predicted = np.empty(prepared.data.n_samples)
    per_fold: dict[str, Accuracy] = {}
    held_out = _held_out(factory, prepared, labels, folds, progress)
    for fold, values in zip(folds, held_out, strict=True):
        test = labels == fold
        predicted[test] = values
        per_fold[fold] = accuracy(prepared.error_um[test], values)
    return Validation(
        scheme=scheme,
        folds=folds,
        per_fold=per_fold,
        pooled=accuracy(prepared.error_um, predicted),
        predicted_um=predicted,
    )


def _held_out(
    factory: ModelFactory, prepared: Prepared, labels: np.ndarray, folds: tuple, progress: bool
) -> list[np.ndarray]:
    """Each fold's rows predicted by a model fitted on the other folds, in fold order.

    Folds are independent, so with many of them (a plant's months of runs) they are
    fitted in worker processes, one per core, each held to one BLAS thread; the
    predictions are the same as fitted one after another.
    """
    workers = min(os.cpu_count() or 1, len(folds))
    if len(folds) < PARALLEL_FROM_FOLDS or workers < 2:
        iterator = tqdm(folds, desc="held-out folds", disable=not progress, leave=False)
        return [_fold(factory, prepared, labels == fold) for fold in iterator]
    from joblib import Parallel, delayed

    jobs = (delayed(_fold_one_thread)(factory, prepared, labels == fold) for fold in folds)
    results = Parallel(n_jobs=workers, return_as="generator")(jobs)  # in order, as they end
    bar = tqdm(
        results, total=len(folds), desc="held-out folds", disable=not progress, leave=False,
        mininterval=0,  # every fold shown as it ends, however fast
    )  # fmt: skip
    return list(bar)


def _fold(factory: ModelFactory, prepared: Prepared, test: np.ndarray) -> np.ndarray:
    model = factory().fit_rows(prepared.inputs, prepared.error_um, ~test)
    return model.predict_rows(prepared.inputs, test)


def _fold_one_thread(factory: ModelFactory, prepared: Prepared, test: np.ndarray) -> np.ndarray:
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        return _fold(factory, prepared, test)


def cross_evaluate(
    factory: ModelFactory,
    prepared: Prepared,
    regime_of_run: dict[str, str],
    progress: bool = False,
) -> tuple[dict[str, ThermalModel], list[SigmaRow]]:
    """One model per run (named after the run), σ of each on every run."""
    runs = prepared.data.run_ids
    masks = {run: prepared.data.run == run for run in runs}
    models: dict[str, ThermalModel] = {}
    rows: list[SigmaRow] = []
    for model_run in tqdm(runs, desc="per-run models", disable=not progress, leave=False):
        train = masks[model_run]
        model = factory().fit(prepared.inputs.take(train), prepared.error_um[train])
        models[model_run] = model
        for data_run in runs:
            test = masks[data_run]
            acc = accuracy(prepared.error_um[test], model.predict(prepared.inputs.take(test)))
            rows.append(
                SigmaRow(
                    model=model_run,
                    model_regime=regime_of_run[model_run],
                    data=data_run,
                    data_regime=regime_of_run[data_run],
                    sigma_um=acc.sigma_um,
                )
            )
    return models, rows
